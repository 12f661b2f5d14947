"""What a render hands out: the :class:`~tofcore.output.frame.Frame`, its files (EXR, PNG, PLY, JSON), the
convergence plot and the dataset reader.
"""
