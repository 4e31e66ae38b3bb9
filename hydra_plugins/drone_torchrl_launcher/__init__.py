"""Hydra launcher ``fused``: runs the jobs of a multirun as one batch of agents in one process."""
