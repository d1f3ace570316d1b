"""Placeholder: being written (lattice free-form deformation)."""


def free_form_deform_points(*args, **kwargs):
    raise NotImplementedError("free_form_deform_points is being written")
