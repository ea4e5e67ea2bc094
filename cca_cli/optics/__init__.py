"""Physics of one capture: FFTs, pupils, the forward model and sensor noise."""
