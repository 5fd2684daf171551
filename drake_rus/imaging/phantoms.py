"""Small synthetic labelled volumes for tests, benchmarks and the fallback training data.

The grid frame V has its axes along the volume's (i, j, k) indices; in a phantom built here
``k`` goes up (z, anterior: the skin is at the top), ``j`` along the body's long axis (y) and
``i`` left-right (x). Every shape is analytic so tests can compare with exact cross-sections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw

from drake_rus.anatomy.labels import Label, LabelVolume


def grid_points(shape: tuple[int, int, int], voxel_size: float) -> tuple[np.ndarray, ...]:
    """Voxel-centre coordinates (m) in V, as three broadcastable arrays."""
    return tuple(
        np.arange(n, dtype=np.float32).reshape([-1 if a == ax else 1 for a in range(3)])
        * voxel_size
        for ax, n in enumerate(shape)
    )


def sphere_volume(
    shape=(80, 80, 80),
    voxel_size=0.001,
    center=(0.04, 0.04, 0.04),
    radius=0.02,
    label=Label.KIDNEY_CORTEX,
    background=Label.SOFT_TISSUE,
) -> LabelVolume:
    """A ball of ``label`` in ``background``."""
    x, y, z = grid_points(shape, voxel_size)
    c = np.asarray(center)
    inside = (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 <= radius**2
    labels = np.where(inside, np.uint8(label), np.uint8(background)).astype(np.uint8)
    return LabelVolume(labels=labels, voxel_size=voxel_size)


def box_volume(
    shape=(80, 80, 80),
    voxel_size=0.001,
    lo=(0.02, 0.02, 0.02),
    hi=(0.05, 0.06, 0.04),
    label=Label.BONE,
    background=Label.SOFT_TISSUE,
) -> LabelVolume:
    """An axis-aligned box [lo, hi] (m, in V) of ``label`` in ``background``."""
    x, y, z = grid_points(shape, voxel_size)
    inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])
    labels = np.where(inside, np.uint8(label), np.uint8(background)).astype(np.uint8)
    return LabelVolume(labels=labels, voxel_size=voxel_size)


@dataclass
class KidneyPhantom:
    """A synthetic abdomen: skin at the top (max k), kidney ellipsoid below, optional rib
    and gas pocket. ``X_VK`` is the kidney ellipsoid's pose, ``semi_axes`` its semi-axes."""

    volume: LabelVolume
    X_VK: RigidTransform
    semi_axes: np.ndarray
    skin_z: float

    def kidney_surface_distance(self, p_V: np.ndarray) -> np.ndarray:
        """Distance (m) of points (N, 3) in V to the kidney ellipsoid's surface, to first
        order near the surface: |f| / |grad f| with f = sum (p_K / a)^2 - 1."""
        p_K = self.X_VK.inverse().multiply(np.asarray(p_V, float).T).T
        a = self.semi_axes
        f = np.sum((p_K / a) ** 2, axis=1) - 1.0
        grad = np.linalg.norm(2.0 * p_K / a**2, axis=1)
        return np.abs(f) / np.maximum(grad, 1e-12)


def kidney_phantom(
    rng: np.random.Generator | None = None,
    shape=(160, 200, 150),
    voxel_size=0.001,
    rib: bool = True,
    gas: bool = True,
    with_internal: bool = True,
) -> KidneyPhantom:
    """A bean-ish kidney (ellipsoid with medulla and sinus) under fat and muscle, with a liver
    slab, optionally a rib bar above one pole and a bowel-gas pocket, at random sizes/poses
    when ``rng`` is given (else the mean values: 110 x 58 x 38 mm kidney, facts "Kidney
    size")."""
    r = rng if rng is not None else None

    def U(lo, hi, mean=None):
        return (lo + hi) / 2 if r is None else r.uniform(lo, hi)

    h = voxel_size
    n = np.asarray(shape)
    ext = n * h
    x, y, z = grid_points(shape, h)
    skin_z = ext[2] - 0.005
    fat_t = U(0.010, 0.025)
    muscle_t = U(0.008, 0.015)
    labels = np.full(shape, np.uint8(Label.SOFT_TISSUE), dtype=np.uint8)
    depth = skin_z - z  # (1, 1, K)
    labels[...] = np.where(depth < 0, np.uint8(Label.OUTSIDE), labels)
    labels[...] = np.where((depth >= 0) & (depth < fat_t), np.uint8(Label.FAT), labels)
    labels[...] = np.where(
        (depth >= fat_t) & (depth < fat_t + muscle_t), np.uint8(Label.MUSCLE), labels
    )
    # Liver: a half-space slab on the superior side (large j), over the kidney's upper pole.
    liver_y = ext[1] * U(0.60, 0.75)
    liver = (y > liver_y + 0.2 * (x - ext[0] / 2)) & (depth > fat_t + muscle_t + 0.003)
    labels[np.broadcast_to(liver, shape)] = Label.LIVER
    # Kidney: semi-axes (m) from length 98-122 mm, width 52-64 mm, thickness 32-44 mm (the
    # facts' 30-45 mm textbook range).
    a = np.array([U(0.049, 0.061), U(0.026, 0.032), U(0.016, 0.022)])
    kd = U(0.060, 0.085)  # skin to kidney centre (m)
    c = np.array([ext[0] / 2 + U(-0.01, 0.01), ext[1] / 2 + U(-0.01, 0.01), skin_z - kd])
    # Long axis roughly along the body (y), tilted: yaw 10-25 deg, pitch 5-20 deg, roll.
    rpy = RollPitchYaw(np.radians(U(-20, 20)), np.radians(U(-15, 15)), np.radians(90 + U(-25, 25)))
    X_VK = RigidTransform(rpy, c)
    R = X_VK.rotation().matrix()
    # Kidney-frame coordinates of every voxel (float32 to keep memory small).
    dx, dy, dz = (x - c[0]), (y - c[1]), (z - c[2])
    kx = dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]
    ky = dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]
    kz = dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2]
    rho2 = (kx / a[0]) ** 2 + (ky / a[1]) ** 2 + (kz / a[2]) ** 2
    # Perirenal fat capsule around the kidney.
    fat_shell = (rho2 <= (1 + 0.006 / a.min()) ** 2) & (rho2 > 1)
    labels[fat_shell] = Label.FAT
    kidney = rho2 <= 1.0
    labels[kidney] = Label.KIDNEY_CORTEX
    if with_internal:
        # Medulla: an inner shell; sinus: the core towards the hilum (+y_K, medial).
        inner = (kx / (a[0] - 0.007)) ** 2 + (ky / (a[1] - 0.007)) ** 2 + (kz / (a[2] - 0.006)) ** 2
        labels[kidney & (inner <= 1.0)] = Label.KIDNEY_MEDULLA
        core = (
            (kx / (0.6 * a[0])) ** 2
            + ((ky - 0.25 * a[1]) / (0.45 * a[1])) ** 2
            + (kz / (0.45 * a[2])) ** 2
        )
        labels[kidney & (core <= 1.0)] = Label.KIDNEY_SINUS
    if rib:
        # A rib bar (about 10 mm thick, 12 mm high) running left-right over the upper pole.
        ry = c[1] + U(0.02, 0.05)
        rz = skin_z - fat_t - muscle_t - U(0.004, 0.010)
        rib_m = (np.abs(y - ry) <= 0.006) & (np.abs(z - rz) <= 0.005) & (x >= 0 * x)
        labels[np.broadcast_to(rib_m, shape)] = Label.BONE
    if gas:
        gc = np.array([c[0] + U(-0.05, -0.03), c[1] + U(-0.06, -0.03), c[2] + U(0.01, 0.03)])
        gr = U(0.008, 0.014)
        gas_m = (x - gc[0]) ** 2 + (y - gc[1]) ** 2 + (z - gc[2]) ** 2 <= gr**2
        labels[gas_m & ~kidney] = Label.GAS
    vol = LabelVolume(labels=labels, voxel_size=h)
    return KidneyPhantom(volume=vol, X_VK=X_VK, semi_axes=a, skin_z=float(skin_z))
