"""What a run leaves on disk: checkpoints, ``episodes.csv``, TensorBoard events and videos."""
