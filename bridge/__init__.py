"""The Zenoh bridge (remote brains, the real-robot link): not built yet."""
