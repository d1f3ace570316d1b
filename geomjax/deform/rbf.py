"""Placeholder: being written (thin-plate-spline RBF deformation)."""


def radial_basis_function_deform_points(*args, **kwargs):
    raise NotImplementedError("radial_basis_function_deform_points is being written")


class ThinPlateSplineFit:
    pass
