"""Run bookkeeping: the runner that drives a recipe's stages in order, the manifest that records
each stage's state, and the lock and signal handling that make a run safe to interrupt."""
