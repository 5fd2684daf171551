"""The simulated patient's contact body (drake_rus.patient_body): a convex hull of the torso
that follows the skin where the probe travels."""

import types

import numpy as np
import trimesh

from drake_rus.anatomy.body_section import crop_body_section
from drake_rus.patient_body import ContactHull, ContactSection, hull_gap_over_kidney
from drake_rus.scenario import ContactConfig


def waisted_body(waist_drop=0.03):
    """A torso along y (x across, z up) whose top is lower by ``waist_drop`` at y = 0 (the
    kidney's level) than at y = +-0.2 m (hips and shoulders), like a patient on the side."""
    y = np.linspace(-0.25, 0.25, 51)
    theta = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    rings = []
    for yk in y:
        height = 0.12 - waist_drop * np.exp(-((yk / 0.15) ** 2))
        rings.append(
            np.column_stack(
                [0.15 * np.cos(theta), np.full_like(theta, yk), 0.12 + height * np.sin(theta)]
            )
        )
    v = np.vstack(rings)
    faces = []
    n = len(theta)
    for i in range(len(y) - 1):
        for j in range(n):
            a, b, c, d = i * n + j, i * n + (j + 1) % n, (i + 1) * n + j, (i + 1) * n + (j + 1) % n
            faces += [[a, c, b], [b, c, d]]
    caps = [len(v), len(v) + 1]
    v = np.vstack([v, [[0.0, y[0], 0.12]], [[0.0, y[-1], 0.12]]])
    for j in range(n):
        faces.append([caps[0], j, (j + 1) % n])
        faces.append([caps[1], (len(y) - 1) * n + (j + 1) % n, (len(y) - 1) * n + j])
    skin = trimesh.Trimesh(v, np.array(faces), process=True)
    trimesh.repair.fix_normals(skin)
    kidney = trimesh.creation.icosphere(radius=1.0)
    kidney.apply_scale([0.025, 0.05, 0.02])
    kidney.apply_translation([0.0, 0.0, 0.12])

    def torso_section(half_length):
        return crop_body_section(skin, np.zeros(3), half_length)

    return types.SimpleNamespace(skin_mesh=skin, kidney_mesh=kidney, torso_section=torso_section)


def test_hull_gap_is_zero_on_a_straight_torso_and_large_on_a_waist():
    straight = waisted_body(0.0)
    assert hull_gap_over_kidney(straight, ContactHull(straight.torso_section(0.2), 300)) < 1e-3
    waist = waisted_body(0.03)
    assert hull_gap_over_kidney(waist, ContactHull(waist.torso_section(0.2), 300)) > 0.015


def test_contact_section_takes_the_longest_section_within_the_gap():
    contact = ContactConfig(patient_hull_max_gap=0.004)
    hull, half_length, gap = ContactSection(waisted_body(0.0), contact)
    assert half_length == 0.20 and gap < 1e-3
    hull, half_length, gap = ContactSection(waisted_body(0.015), contact)
    assert half_length < 0.20 and gap <= 0.004
    longer = [h for h in contact.patient_section_half_lengths if h > half_length]
    body = waisted_body(0.015)
    for h in longer:  # every longer section bridges the waist more than allowed
        assert hull_gap_over_kidney(body, ContactHull(body.torso_section(h), 300)) > 0.004


def test_contact_section_falls_back_to_the_best_with_a_warning(caplog):
    contact = ContactConfig(patient_hull_max_gap=1e-6, patient_section_half_lengths=[0.2, 0.1])
    _, half_length, gap = ContactSection(waisted_body(0.03), contact)
    assert half_length == 0.1 and gap > 1e-6
    assert "contact hull lies" in caplog.text
