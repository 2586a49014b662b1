"""The MuJoCo physics core (`core`), the MJCF it compiles (`scene`), the read-only accessor robot
modules use for the model and data (`access`), and offscreen rendering (`offscreen`)."""
