"""Annotated ultrasound frames on disk, in the Open Kidney Ultrasound Data Set's mask layout.

The Open Kidney Ultrasound Data Set (Singla et al. 2023; ``docs/facts/segmentation_data.md``)
gives, for each B-mode PNG image, a kidney-capsule mask: a PNG of the image's size, the
image's file name, 1 inside the capsule polygon and 0 elsewhere (its ``create_masks`` writes
``capsule/NAME.png``; a second mask, ``regions/NAME.png``, labels the central echo complex 1,
medulla 2 and cortex 3 inside it). The capsule is the kidney's outline: our segmentation
target. A folder of frames here is:

    DIR/images/NAME.png    the frame: 8-bit grey (a colour PNG is converted to grey), on the
                           probe's image grid (imaging.image_height_px x image_width_px, the
                           fan of imaging.depth, as the station's ``us_image`` gives it)
    DIR/capsule/NAME.png   its kidney mask, the same size: > 0 inside the kidney's capsule
                           (1 as the data set writes it, or 255), 0 outside
    DIR/regions/NAME.png   optional, not read (the data set's inner regions)
    DIR/frames.csv         optional, one row per frame: ``name`` (NAME), ``kidney`` (1: the
                           frame shows the kidney, 0: it does not), ``depth_m`` (the imaging
                           depth of the frame, m); ``drake-rus scan --save-frames`` also
                           records ``frame_index``, ``time_s`` (s), ``phase`` and the probe
                           pose X_BP: ``p_BP_x_m``, ``p_BP_y_m``, ``p_BP_z_m`` (m, in the
                           robot base B) and the quaternion ``q_BP_w``, ``q_BP_x``,
                           ``q_BP_y``, ``q_BP_z``

Every image needs its mask. A mask without a kidney pixel is refused unless ``frames.csv``
marks the frame ``kidney`` 0 (an annotation left blank is not a kidney-free frame). A bad
folder raises :class:`FramesError` with one line naming the file and what was expected; the
reader only reads.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

IMAGES, MASKS, TABLE = "images", "capsule", "frames.csv"
POSE_COLUMNS = ("p_BP_x_m", "p_BP_y_m", "p_BP_z_m", "q_BP_w", "q_BP_x", "q_BP_y", "q_BP_z")
COLUMNS = ("name", "frame_index", "time_s", "phase", "kidney", "depth_m") + POSE_COLUMNS


class FramesError(ValueError):
    """A folder of annotated frames that cannot be used; the message is one line."""


@dataclass
class AnnotatedFrames:
    """Frames read from a folder: ``images`` (N, rows, cols) uint8 grey, ``masks`` (N, rows,
    cols) bool kidney, ``names`` (N,), ``depth`` (N,) imaging depth (m), ``kidney`` (N,)
    bool: the frame shows the kidney, and the ``frames.csv`` rows (dicts; empty without)."""

    images: np.ndarray
    masks: np.ndarray
    names: list
    depth: np.ndarray
    kidney: np.ndarray
    rows: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.names)

    def subset(self, index) -> "AnnotatedFrames":
        index = np.asarray(index, int)
        return AnnotatedFrames(
            self.images[index],
            self.masks[index],
            [self.names[i] for i in index],
            self.depth[index],
            self.kidney[index],
            [self.rows[i] for i in index] if self.rows else [],
        )


def _read_png(path: Path, what: str) -> np.ndarray:
    """A PNG as a 2-D array (grey: colour converted, alpha dropped)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.format != "PNG":
                raise FramesError(f"{path}: a {im.format} file; {what} must be a PNG image")
            if im.mode in ("I;16", "I;16B", "I", "F", "1", "L", "P"):
                arr = np.asarray(im.convert("L") if im.mode in ("1", "P") else im)
            else:
                arr = np.asarray(im.convert("L"))
    except FramesError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        raise FramesError(f"{path}: not a readable PNG image; {what} must be a PNG") from None
    return np.asarray(arr)


def _grey8(arr: np.ndarray, path: Path) -> np.ndarray:
    if arr.dtype == np.uint8:
        return arr
    if arr.dtype.kind in "ui" and arr.max(initial=0) <= 255:
        return arr.astype(np.uint8)
    raise FramesError(f"{path}: {arr.dtype} grey levels up to {arr.max()}; expected 8-bit grey")


def _files(folder: Path) -> dict:
    """{stem: path} of the visible files in a folder (two files of one name: FramesError)."""
    out = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.stem in out:
            raise FramesError(f"{p}: a second file named {p.stem!r} beside {out[p.stem].name}")
        out[p.stem] = p
    return out


def _read_table(path: Path) -> dict:
    """{name: row} of a frames.csv."""
    try:
        # utf-8-sig: a table saved by a spreadsheet ("CSV UTF-8") starts with a byte-order
        # mark, which would otherwise become part of the first column's name.
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise FramesError(f"{path}: cannot be read as text ({e})") from None
    reader = csv.DictReader(io.StringIO(text), skipinitialspace=True)
    if reader.fieldnames:
        # "name, kidney, depth_m": a column is known by its name without the spaces around it
        reader.fieldnames = [f.strip() for f in reader.fieldnames]
    if not reader.fieldnames or "name" not in reader.fieldnames:
        raise FramesError(
            f"{path}: expected a header with a 'name' column, got {reader.fieldnames}"
        )
    rows = {}
    for line, row in enumerate(reader, start=2):
        name = (row.get("name") or "").strip()
        if not name:
            raise FramesError(f"{path}, line {line}: empty 'name'")
        if name in rows:
            raise FramesError(f"{path}, line {line}: frame {name!r} listed twice")
        for key, check in (("kidney", _flag), ("depth_m", _depth)):
            value = (row.get(key) or "").strip()
            if value:
                try:
                    row[key] = check(value)
                except ValueError as e:
                    raise FramesError(f"{path}, line {line}: '{key}' {e}") from None
            else:
                row[key] = None
        rows[name] = row
    return rows


def _flag(value: str) -> bool:
    if value not in ("0", "1"):
        raise ValueError(f"must be 0 or 1, got {value!r}")
    return value == "1"


def _depth(value: str) -> float:
    d = float(value)
    if not (math.isfinite(d) and 0.03 <= d <= 0.4):
        raise ValueError(f"must be an imaging depth in m (0.03-0.4), got {value!r}")
    return d


def read_annotated_frames(
    folder, image_shape: tuple[int, int], depth: float | None = None
) -> AnnotatedFrames:
    """Reads a folder of annotated frames (the layout in the module docstring).

    ``image_shape`` (rows, cols): the probe's image grid every frame must have; ``depth``
    (m): the imaging depth of frames that ``frames.csv`` gives none for (None: every frame
    needs its ``depth_m``). Raises :class:`FramesError` (one line naming the file) on: no
    ``images`` folder or no image in it, a file there that is not a PNG image, an image
    without its mask (or a mask without its image), a mask of another size than its image,
    an image of another size than ``image_shape``, a mask without a kidney pixel for a frame
    not marked ``kidney`` 0, a frame without a depth."""
    root = Path(folder)
    if not root.is_dir():
        raise FramesError(f"--frames: {root} is not a folder")
    img_dir, mask_dir = root / IMAGES, root / MASKS
    if not img_dir.is_dir():
        raise FramesError(
            f"{root}: no '{IMAGES}' folder; expected {IMAGES}/NAME.png with {MASKS}/NAME.png "
            "(the Open Kidney Ultrasound Data Set's layout)"
        )
    images = _files(img_dir)
    if not images:
        raise FramesError(f"{img_dir}: no image in it")
    masks = _files(mask_dir) if mask_dir.is_dir() else {}
    table = _read_table(root / TABLE) if (root / TABLE).is_file() else {}
    for name, path in images.items():
        if path.suffix.lower() != ".png":
            raise FramesError(f"{path}: not a PNG image; {IMAGES}/ holds the frames as NAME.png")
        if name not in masks:
            raise FramesError(
                f"{path}: no mask {mask_dir / (name + '.png')}; every frame needs its kidney "
                "mask (> 0 inside the kidney's capsule)"
            )
    for name, path in masks.items():
        if name not in images:
            raise FramesError(f"{path}: a mask without its image {img_dir / (name + '.png')}")
        if path.suffix.lower() != ".png":
            raise FramesError(f"{path}: not a PNG image; {MASKS}/ holds the masks as NAME.png")
    for name in table:
        if name not in images:
            raise FramesError(f"{root / TABLE}: lists {name!r}, which has no image in {img_dir}")
    names = sorted(images)
    n = len(names)
    shape = tuple(int(v) for v in image_shape)
    out_img = np.zeros((n,) + shape, np.uint8)
    out_mask = np.zeros((n,) + shape, bool)
    depths = np.zeros(n)
    kidney = np.zeros(n, bool)
    for i, name in enumerate(names):
        img = _grey8(_read_png(images[name], "a frame"), images[name])
        mask = _read_png(masks[name], "a mask")
        if mask.shape != img.shape:
            raise FramesError(
                f"{masks[name]}: {mask.shape[0]} x {mask.shape[1]} px, but its image is "
                f"{img.shape[0]} x {img.shape[1]} px; a mask has its image's size"
            )
        if img.shape != shape:
            raise FramesError(
                f"{images[name]}: {img.shape[0]} x {img.shape[1]} px; frames must be on the "
                f"probe's image grid, {shape[0]} x {shape[1]} px (imaging.image_height_px x "
                "image_width_px)"
            )
        row = table.get(name, {})
        has = bool(np.any(mask > 0))
        marked = row.get("kidney")
        if not has and marked is not False:
            raise FramesError(
                f"{masks[name]}: no kidney pixel; annotate the kidney, or mark a frame without "
                f"it kidney 0 in {root / TABLE}"
            )
        d = row.get("depth_m") if row.get("depth_m") is not None else depth
        if d is None:
            raise FramesError(
                f"{images[name]}: no imaging depth; give depth_m in {root / TABLE} or --depth-m"
            )
        out_img[i], out_mask[i], depths[i], kidney[i] = img, mask > 0, d, has
    return AnnotatedFrames(
        out_img, out_mask, names, depths, kidney, [table.get(k, {"name": k}) for k in names]
    )


@dataclass(frozen=True)
class SavedFrame:
    """One frame of a scan for ``--save-frames``: grey image and kidney mask (rows, cols),
    capture time (s), frame index, supervisor phase name, the segmenter's visible flag and
    the probe pose X_BP (RigidTransform, P in B)."""

    image: np.ndarray
    mask: np.ndarray
    time: float
    frame_index: int
    phase: str
    visible: bool
    X_BP: object


def _png_bytes(arr: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr, np.uint8), mode="L").save(buf, format="PNG")
    return buf.getvalue()


def frame_rows(frames, depth) -> list[dict]:
    """The ``frames.csv`` rows of saved frames (names by frame index, 6 digits); ``depth``
    (m): the imaging depth of every frame, or one per frame."""
    depths = np.broadcast_to(np.asarray(depth, float), (len(frames),))
    rows = []
    for f, depth in zip(frames, depths):
        q = f.X_BP.rotation().ToQuaternion()
        p = f.X_BP.translation()
        rows.append(
            {
                "name": f"{f.frame_index:06d}",
                "frame_index": f.frame_index,
                "time_s": f"{f.time:.4f}",
                "phase": f.phase,
                "kidney": int(bool(f.visible)),
                "depth_m": f"{depth:g}",
                **{k: f"{v:.6f}" for k, v in zip(POSE_COLUMNS[:3], p)},
                **{k: f"{v:.8f}" for k, v in zip(POSE_COLUMNS[3:], (q.w(), q.x(), q.y(), q.z()))},
            }
        )
    return rows


def write_annotated_frames(folder, frames, depth) -> Path:
    """Writes saved frames (:class:`SavedFrame`) as a folder in the layout of this module:
    ``images/``, ``capsule/`` (the segmenter's mask, 1 inside, ready to correct in an
    annotation tool) and ``frames.csv`` (kidney = the segmenter's visible flag; ``depth``
    (m): one for all frames or one per frame). The folder
    is filled under a temporary name and renamed when whole; an existing non-empty folder is
    refused (FramesError)."""
    root = Path(folder)
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise FramesError(f"--save-frames: {root} exists and is not an empty folder")
    tmp = root.with_name(f".{root.name}.partial")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    (tmp / IMAGES).mkdir(parents=True)
    (tmp / MASKS).mkdir()
    rows = frame_rows(frames, depth)
    for f, row in zip(frames, rows):
        (tmp / IMAGES / f"{row['name']}.png").write_bytes(_png_bytes(f.image))
        (tmp / MASKS / f"{row['name']}.png").write_bytes(_png_bytes(np.asarray(f.mask, bool)))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    (tmp / TABLE).write_text(buf.getvalue())
    if root.exists():
        root.rmdir()
    tmp.rename(root)
    return root
