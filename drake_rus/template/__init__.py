"""drake-rus template: the canonical kidney frame (eq. 13-14), the kidney template (eq. 15)
and its statistical shape model. ``load_template()`` reads ``models/kidney_template.npz``."""

from drake_rus.template.pca import canonical_frame, mesh_canonical_frame
from drake_rus.template.io import Template, load_template, DEFAULT_TEMPLATE_PATH

__all__ = ["canonical_frame", "mesh_canonical_frame", "Template", "load_template",
           "DEFAULT_TEMPLATE_PATH"]
