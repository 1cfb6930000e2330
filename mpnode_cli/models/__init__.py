"""Learned simulators: MP-NODE and (later) its baselines, by name in `registry`."""
