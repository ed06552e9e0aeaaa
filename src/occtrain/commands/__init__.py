"""What the commands do beyond running a recipe: evaluate a stage, score prediction files,
compare a run with the papers, plan a stage's memory. ``occtrain.cli`` parses the command line
and calls these."""
