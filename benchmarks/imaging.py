"""Imaging speed and segmentation accuracy (``python -m benchmarks imaging``).

Speed, on one thread, default scenario imaging (256 x 256 image, 128 scan lines):
- ``fps_slice``: oblique slicing of a held-out patient's label volume;
- ``fps_slice_emulate``: + ultrasound emulation;
- ``fps_full``: + segmentation and the mask read-outs (visible, c_msk, boundary pixels), with
  the learned (onnx) backend when its model exists, else the classical one
  (``fps_full_backend`` says which; ``fps_full_classical`` / ``fps_full_onnx`` give both).
Frames per CPU second of this process (``time.process_time``), which the other jobs on a
shared machine disturb less than wall-clock time, best of 3 passes; ``wall_fps_*`` are the
wall-clock rates. ``load_average`` says how busy the machine was.

Accuracy: mean IoU against the true kidney mask over emulated frames (kidney area >= the
scenario's ``min_kidney_area``) of held-out test patients ``test:0..N-1``, which training never
uses (it uses ``train:K``): ``iou_classical`` and ``iou_onnx`` (null if no model).
The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def _rate(fn, items, repeat: int = 3):
    """(frames per CPU second, frames per wall second), best of ``repeat`` passes (the
    least disturbed by other jobs, as ``timeit`` does)."""
    best_cpu = best_wall = float("inf")
    for _ in range(repeat):
        t_cpu, t_wall = time.process_time(), time.perf_counter()
        for it in items:
            fn(it)
        best_cpu = min(best_cpu, time.process_time() - t_cpu)
        best_wall = min(best_wall, time.perf_counter() - t_wall)
    n = len(items)
    return n / max(best_cpu, 1e-9), n / max(best_wall, 1e-9)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks imaging", description=__doc__)
    ap.add_argument("--frames", type=int, default=200, help="frames per speed measurement")
    ap.add_argument("--patients", type=int, default=3, help="test patients for the IoU")
    ap.add_argument("--iou-frames", type=int, default=60, help="frames per test patient")
    ap.add_argument("--source", default="test", help="'test' (test:K patients) or 'phantom'")
    args = ap.parse_args(argv)

    from pydrake.math import RigidTransform

    from drake_rus.imaging.config import ImagingConfig
    from drake_rus.imaging.dataset import ViewSampler
    from drake_rus.imaging.emulator import EmulatorModel, emulate
    from drake_rus.imaging.evaluation import load_volume, make_source_frames, mean_iou
    from drake_rus.imaging.onnx_backend import OnnxSegmenter, resolve_model_path
    from drake_rus.imaging.probe import ProbeGeometry
    from drake_rus.imaging.segment import read_mask, segment_classical
    from drake_rus.imaging.slicing import slice_volume

    cfg = ImagingConfig()
    g = ProbeGeometry.from_config(cfg)
    model = EmulatorModel.from_config(cfg, g)
    specs = ([f"test:{k}" for k in range(args.patients)] if args.source == "test"
             else [f"phantom:{5000 + k}" for k in range(args.patients)])
    t0 = time.perf_counter()
    vol, up = load_volume(specs[0])
    sampler = ViewSampler(vol, up)
    rng = np.random.default_rng(0)
    poses = [p for p in (sampler.sample(rng) for _ in range(args.frames)) if p is not None]
    X_BV = RigidTransform()
    labels = [slice_volume(g, vol, X_BV, X) for X in poses]
    images = [emulate(lab, model, 0, i) for i, lab in enumerate(labels)]

    onnx_path = resolve_model_path(cfg.onnx_model)
    onnx = OnnxSegmenter.from_config(cfg, g) if onnx_path.is_file() else None
    classical = lambda us: segment_classical(us, g, None, cfg.min_kidney_area)

    def full(segment):
        def run(i):
            lab = slice_volume(g, vol, X_BV, poses[i])
            us = emulate(lab, model, 0, i)
            read_mask(segment(us), g, cfg.min_kidney_area)
        return run

    idx = list(range(len(poses)))
    fps_slice, wall_slice = _rate(lambda i: slice_volume(g, vol, X_BV, poses[i]), idx)
    fps_se, wall_se = _rate(lambda i: emulate(slice_volume(g, vol, X_BV, poses[i]), model, 0, i),
                            idx)
    fps_cl, wall_cl = _rate(full(classical), idx)
    fps_on = wall_on = None
    if onnx is not None:
        fps_on, wall_on = _rate(full(onnx), idx)
    seg_only_onnx = _rate(lambda i: onnx(images[i]), idx)[0] if onnx is not None else None
    seg_only_classical = _rate(lambda i: classical(images[i]), idx)[0]

    ious_cl, ious_on, details = [], [], {}
    for k, spec in enumerate(specs):
        frames = make_source_frames(spec, model, args.iou_frames, seed=777 + k)
        r_cl = mean_iou(classical, frames, g, cfg.min_kidney_area)
        r_on = mean_iou(onnx, frames, g, cfg.min_kidney_area) if onnx is not None else None
        details[spec] = {"classical": r_cl, "onnx": r_on}
        ious_cl.append(r_cl["iou"])
        if r_on is not None:
            ious_on.append(r_on["iou"])
        print(f"{spec}: classical IoU {r_cl['iou']:.3f}"
              + (f", onnx IoU {r_on['iou']:.3f}" if r_on else "")
              + f" ({r_cl['frames_with_kidney']} frames with kidney)", flush=True)

    r = lambda x: None if x is None else round(float(x), 3)
    result = {
        "fps_slice": r(fps_slice),
        "fps_slice_emulate": r(fps_se),
        "fps_full": r(fps_on if fps_on is not None else fps_cl),
        "iou_classical": r(np.mean(ious_cl)),
        "iou_onnx": r(np.mean(ious_on)) if ious_on else None,
        "fps_full_backend": "onnx" if fps_on is not None else "classical",
        "fps_full_classical": r(fps_cl),
        "fps_full_onnx": r(fps_on),
        "fps_segment_only_onnx": r(seg_only_onnx),
        "fps_segment_only_classical": r(seg_only_classical),
        "wall_fps_slice": r(wall_slice), "wall_fps_slice_emulate": r(wall_se),
        "wall_fps_full": r(wall_on if wall_on is not None else wall_cl),
        "image_shape": list(g.image_shape),
        "iou_sources": specs, "iou_frames_per_source": args.iou_frames,
        "iou_details": details,
        "onnx_model": str(onnx_path) if onnx is not None else None,
        "seconds": round(time.perf_counter() - t0, 1),
        "load_average": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
