"""The core: the AMR data model and its validation, boxes, levels, derived fields, the kd-tree,
the .npz layout and the float64 reference model. NumPy only (no Dr.Jit, no Mitsuba)."""
