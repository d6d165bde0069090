"""The Mitsuba layer: the amr_iso integrator and what it is made of (options, per-frame
inputs, shading, layering, AOVs), loading scenes, and the camera."""
