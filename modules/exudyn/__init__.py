"""The Exudyn physics core (`core`) and the parts it builds the Exudyn system from: topology and
plans of bodies and joints, the system and its outputs, kinematic trees, contacts, ANCF cables."""
