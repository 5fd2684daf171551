"""drake-rus anatomy: virtual patients from published statistics and real-data import.

``load_patient("seed:3")``, ``load_patient("test:0")``, ``load_patient("../shared/anatomy/
hubmap_vh_female")`` all return a :class:`Patient` in the patient frame Pt (the bed frame),
from the on-disk patient cache when it was built before (:mod:`drake_rus.anatomy.cache`).
"""

from drake_rus.anatomy.cohort import cohort_seeds, load_patient
from drake_rus.anatomy.generator import generate_patient
from drake_rus.anatomy.importers import patient_from_label_map, patient_from_meshes
from drake_rus.anatomy.labels import KIDNEY_LABELS, Label, LabelVolume, is_kidney
from drake_rus.anatomy.patient import Patient

__all__ = [
    "Label",
    "LabelVolume",
    "KIDNEY_LABELS",
    "is_kidney",
    "Patient",
    "generate_patient",
    "patient_from_meshes",
    "patient_from_label_map",
    "load_patient",
    "cohort_seeds",
]
