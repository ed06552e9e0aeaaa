"""What every family shares, naming none: token sequences and their builder, the greedy decoder,
the joint vocabulary, the task and operation seams, the scorers, the registry."""
