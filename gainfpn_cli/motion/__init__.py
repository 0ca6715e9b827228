"""Motion: where each reference pixel is seen in every other frame (docs/method.md section 3)."""

#: Every model fitted frame by frame, simplest first: the global warps (:mod:`motion.fit`), then the
#: homography plus a smooth field (:mod:`motion.fields`).
MODELS = ("translation", "affine", "homography", "rolling", "mesh")
#: Every model: those, and scene layers (:mod:`motion.layers`), fitted to the whole burst at once.
ALL_MODELS = (*MODELS, "layers")
