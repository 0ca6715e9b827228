"""The gain solvers, their result and the FPN models (docs/method.md sections 8 to 11)."""

#: The gain-FPN models :mod:`solve.fpnmodel` chooses from, fewest parameters first.
FPN_MODELS = ("none", "row", "column", "column+row", "pixel")
