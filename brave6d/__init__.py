"""brave6d stage."""
