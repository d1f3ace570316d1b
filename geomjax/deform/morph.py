"""Placeholder: being written (compact Wendland-C2 Shepard morphing)."""


def morph_points(*args, **kwargs):
    raise NotImplementedError("morph_points is being written")
