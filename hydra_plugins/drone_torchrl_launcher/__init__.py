"""Our Hydra plug-ins: one launcher that trains a sweep as one batch (``fused``, ``population`` and the searches), the population sweeper, and the SLURM launchers."""
