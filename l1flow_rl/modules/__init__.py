"""The TensorDictModules a user composes, and their parts: the L1 Flow actor and its chunk policy,
the observation and action normalisers, the EMA of the weights, and the observation reader."""
