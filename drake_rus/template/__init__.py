"""drake-rus template: the kidney template (eq. 15) and its statistical shape model, built on
the canonical kidney frame of ``drake_rus.anatomy.canonical_frame`` (eq. 13-14).
``load_template()`` reads ``models/kidney_template.npz``."""

from drake_rus.template.io import DEFAULT_TEMPLATE_PATH, Template, load_template

__all__ = ["Template", "load_template", "DEFAULT_TEMPLATE_PATH"]
