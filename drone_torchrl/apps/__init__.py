"""The command-line apps: thin ``@hydra.main`` / argparse shells over library functions."""
