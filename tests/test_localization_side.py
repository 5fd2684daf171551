"""A template of one side's kidneys registered to the other side's kidney: mirrored
through the sagittal plane (RegistrationTemplate.for_side), as the left kidney is the right
one's mirror image."""

import dataclasses

import numpy as np
import pytest
from pydrake.math import RotationMatrix

from drake_rus.localization.config import LocalizationConfig
from drake_rus.localization.localize import (
    RegistrationTemplate,
    load_registration_template,
    localize,
)

FLIP = np.array([1.0, 1.0, -1.0])


def chiral_kidney(n: int = 3000) -> RegistrationTemplate:
    """A right kidney in its canonical frame K (m): a 110 x 56 x 40 mm ellipsoid whose
    anteromedial part (y_k < 0, z_k > 0: the hilum's anterior lip of a right kidney)
    bulges 8 mm, so the shape is not its own mirror image through z_k."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    semi = np.array([0.055, 0.028, 0.020])
    p = u * semi
    bump = 0.008 * np.exp(-((p[:, 1] + 0.028) ** 2 + (p[:, 2] - 0.02) ** 2) / 0.012**2)
    normals = p / semi**2
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    p = p + bump[:, None] * normals
    return RegistrationTemplate(p - p.mean(axis=0), normals, side="right")


def test_for_side_mirrors_only_the_other_side():
    t = chiral_kidney(200)
    t = dataclasses.replace(
        t, modes=np.random.default_rng(1).normal(size=(2, 200, 3)), variances=np.ones(2)
    )
    assert t.for_side("right") is t
    left = t.for_side("left")
    assert left.side == "left"
    np.testing.assert_array_equal(left.points, t.points * FLIP)
    np.testing.assert_array_equal(left.normals, t.normals * FLIP)
    np.testing.assert_array_equal(left.modes, t.modes * FLIP)
    np.testing.assert_array_equal(left.variances, t.variances)
    assert left.for_side("left") is left
    np.testing.assert_array_equal(left.for_side("right").points, t.points)
    assert t.for_side("left") is left and left.for_side("right") is t  # made once
    unknown = dataclasses.replace(t, side=None)
    assert unknown.for_side("left") is unknown  # a file that does not say: as it is
    with pytest.raises(ValueError, match="side: expected one of"):
        t.for_side("both")


def test_the_shipped_template_says_it_is_of_right_kidneys():
    assert load_registration_template().side == "right"


def test_a_left_kidney_registers_to_the_mirrored_right_template():
    """The left kidney is the right template's shape reflected through z_k, posed in B by
    the left side's canonical frame (x_k superior, y_k to the patient's left). The right
    template itself cannot be rotated onto it; the mirrored one fits it exactly."""
    right = chiral_kidney()
    superior_B, lateral_B = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    R_BK = np.column_stack([superior_B, lateral_B, np.cross(superior_B, lateral_B)])
    R_true = RotationMatrix.MakeZRotation(0.1) @ RotationMatrix(R_BK)
    p_BK = np.array([0.5, 0.0, 0.1])
    P_B = (R_true.matrix() @ (right.points * FLIP).T).T + p_BK
    config = LocalizationConfig(method="seed")
    as_is = localize(P_B, right, config, superior_B, lateral_B)
    mirrored = localize(P_B, right.for_side("left"), config, superior_B, lateral_B)
    assert mirrored.rms_residual < 0.05e-3  # 0.01 mm
    assert np.linalg.norm(mirrored.X_BK.translation() - p_BK) < 0.05e-3
    assert as_is.rms_residual > 0.4e-3  # 0.7 mm: the bulge on the wrong side
