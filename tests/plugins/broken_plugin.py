"""A plugin that fails while being imported with something other than an ImportError (a
setting it reads is missing): a command names it in one line, never with its traceback."""

raise RuntimeError("the broken plugin's settings are missing\nthis second line stays out of the error")
