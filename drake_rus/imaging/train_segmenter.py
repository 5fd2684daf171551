"""Trains the learned kidney segmenter and exports it to ONNX (needs the ``train`` extra).

Data recipe (``drake_rus.imaging.dataset``): for each training patient (``train:K``, never a
``test:K`` one), ``--frames`` probe views looking down at the kidney through the upper skin
(random kidney point, up to 25 mm lateral offset, up to 25 deg tilt, random array rotation),
each sliced, emulated with the scenario's default emulator (speckle seeded per frame) and
labelled with the true kidney mask. Images and masks are reduced to the model's input size
(2x2 block mean; mask = block majority).

Model: a small U-Net on a 64 x 64 input (the 256 x 256 image reduced by 4 x 4 block means,
which also averages the speckle away), 3 poolings, ``--width`` channels at full resolution
doubling per level, 1 input channel (grey / 255), 1 output channel (kidney logit) at 64 x 64;
the backend upsamples the probability bilinearly to the image before thresholding. Loss: BCE + soft Dice.
Augmentation: left-right flips and a random gain / contrast change of the grey levels.

    .venv/bin/pip install torch==2.13.0 onnx
    nice .venv/bin/python -m drake_rus.imaging.train_segmenter --patients 12 --frames 200 \\
        --epochs 10 --out models/segmenter

Writes ``kidney_unet.onnx`` and ``kidney_unet.json`` (shapes, normalisation, recipe); the
held-out IoU comes from ``python -m benchmarks imaging`` and is recorded there by hand.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from drake_rus.imaging.config import ImagingConfig
from drake_rus.imaging.emulator import EmulatorModel
from drake_rus.imaging.evaluation import make_source_frames
from drake_rus.imaging.onnx_backend import resize_to
from drake_rus.imaging.probe import ProbeGeometry


def reduce_frames(frames, size: int):
    """(images float32 (N, size, size) in [0, 1], masks float32 (N, size, size))."""
    X = np.stack([resize_to(us, size, size) / 255.0 for us, *_ in frames]).astype(np.float32)
    Y = np.stack([resize_to(m.astype(np.float32), size, size) > 0.5
                  for _, m, *_ in frames]).astype(np.float32)
    return X, Y


def build_dataset(sources: list[str], frames_per_source: int, size: int, cache: Path | None,
                  seed: int = 0, config: ImagingConfig | None = None):
    """Emulated training images and masks from ``sources``, cached as .npz per source."""
    config = config or ImagingConfig()
    model = EmulatorModel.from_config(config, ProbeGeometry.from_config(config))
    Xs, Ys = [], []
    for i, spec in enumerate(sources):
        path = None
        if cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
            path = cache / f"{spec.replace(':', '_')}_{frames_per_source}_{size}_{seed}.npz"
            if path.is_file():
                d = np.load(path)
                Xs.append(d["X"])
                Ys.append(d["Y"])
                continue
        t = time.time()
        frames = make_source_frames(spec, model, frames_per_source, seed=seed * 1000 + i)
        X, Y = reduce_frames(frames, size)
        if path is not None:
            np.savez_compressed(path, X=X, Y=Y)
        print(f"data {spec}: {len(X)} frames in {time.time() - t:.0f} s", flush=True)
        Xs.append(X)
        Ys.append(Y)
    return np.concatenate(Xs), np.concatenate(Ys)


def make_unet(width: int = 8, lite: bool = False):
    """A small U-Net; ``lite``: one convolution (not two) in the full-resolution blocks."""
    import torch
    from torch import nn

    def block(cin, cout, convs=2):
        layers = []
        for k in range(convs):
            layers += [nn.Conv2d(cin if k == 0 else cout, cout, 3, padding=1, bias=False),
                       nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]
        return nn.Sequential(*layers)

    full_res_convs = 1 if lite else 2

    class UNet(nn.Module):
        def __init__(self, w):
            super().__init__()
            self.e1, self.e2 = block(1, w, full_res_convs), block(w, 2 * w)
            self.e3, self.b = block(2 * w, 4 * w), block(4 * w, 4 * w)
            self.pool = nn.MaxPool2d(2)
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False)
            self.d3 = block(8 * w, 2 * w)
            self.d2 = block(4 * w, w)
            self.d1 = block(2 * w, w, full_res_convs)
            self.head = nn.Conv2d(w, 1, 1)

        def forward(self, x):
            e1 = self.e1(x)
            e2 = self.e2(self.pool(e1))
            e3 = self.e3(self.pool(e2))
            b = self.b(self.pool(e3))
            d3 = self.d3(torch.cat([self.up(b), e3], 1))
            d2 = self.d2(torch.cat([self.up(d3), e2], 1))
            d1 = self.d1(torch.cat([self.up(d2), e1], 1))
            return self.head(d1)

    return UNet(width)


def train(X, Y, width: int, epochs: int, batch: int = 16, lr: float = 3e-3, seed: int = 0,
          threads: int = 1, log=print, lite: bool = False):
    import torch
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    net = make_unet(width, lite)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    steps = epochs * int(np.ceil(len(X) / batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    Xt = torch.from_numpy(X[:, None])
    Yt = torch.from_numpy(Y[:, None])
    rng = np.random.default_rng(seed)
    bce = torch.nn.BCEWithLogitsLoss()
    for epoch in range(epochs):
        net.train()
        order = rng.permutation(len(X))
        total, t0 = 0.0, time.time()
        for k in range(0, len(order), batch):
            idx = order[k:k + batch]
            x, y = Xt[idx].clone(), Yt[idx].clone()
            flip = torch.from_numpy(rng.random(len(idx)) < 0.5)
            x[flip] = x[flip].flip(-1)
            y[flip] = y[flip].flip(-1)
            # Gain / contrast jitter (a different machine setting or patient habitus).
            g = torch.from_numpy(rng.uniform(0.8, 1.2, (len(idx), 1, 1, 1)).astype(np.float32))
            c = torch.from_numpy(rng.uniform(-0.08, 0.08, (len(idx), 1, 1, 1)).astype(np.float32))
            x = torch.where(x > 0, (x * g + c).clamp(0, 1), x)
            logits = net(x)
            p = torch.sigmoid(logits)
            inter = (p * y).sum((1, 2, 3))
            dice = 1 - (2 * inter + 1) / (p.sum((1, 2, 3)) + y.sum((1, 2, 3)) + 1)
            loss = bce(logits, y) + dice.mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
        log(f"epoch {epoch + 1}/{epochs}: loss {total / len(X):.4f} ({time.time() - t0:.0f} s)")
    net.eval()
    return net


def export_onnx(net, path: Path, size: int):
    import torch
    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 1, size, size)
    torch.onnx.export(net, dummy, str(path), input_names=["image"], output_names=["logits"],
                      opset_version=17, dynamo=False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--patients", type=int, default=8, help="training patients train:0..N-1")
    ap.add_argument("--frames", type=int, default=160, help="frames per patient")
    ap.add_argument("--phantoms", type=int, default=0, help="also N synthetic phantoms")
    ap.add_argument("--size", type=int, default=64, help="model input size (pixels)")
    ap.add_argument("--data-size", type=int, default=128,
                    help="size the cached data is kept at (a multiple of --size)")
    ap.add_argument("--width", type=int, default=8, help="U-Net channels at full resolution")
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--lite", action="store_true",
                    help="one convolution per full-resolution block (faster inference)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default="/tmp/drake_rus_segmenter_data")
    ap.add_argument("--out", default="models/segmenter")
    ap.add_argument("--data-only", action="store_true")
    args = ap.parse_args(argv)
    sources = [f"train:{k}" for k in range(args.patients)]
    sources += [f"phantom:{1000 + k}" for k in range(args.phantoms)]
    X, Y = build_dataset(sources, args.frames, args.data_size, Path(args.cache))
    if args.size != args.data_size:
        f = args.data_size // args.size
        X = X.reshape(len(X), args.size, f, args.size, f).mean(axis=(2, 4))
        Y = (Y.reshape(len(Y), args.size, f, args.size, f).mean(axis=(2, 4)) > 0.5)
        Y = Y.astype(np.float32)
    print(f"dataset: {len(X)} frames, kidney in {(Y.sum((1, 2)) > 0).mean():.0%}", flush=True)
    if args.data_only:
        return 0
    t = time.time()
    net = train(X, Y, args.width, args.epochs, threads=args.threads,
                log=lambda s: print(s, flush=True), lite=args.lite)
    out = Path(args.out)
    onnx_path = out / "kidney_unet.onnx"
    export_onnx(net, onnx_path, args.size)
    meta = {
        "model": onnx_path.name,
        "input": {"name": "image", "shape": [1, 1, args.size, args.size], "dtype": "float32",
                  "normalisation": (f"grey / 255 (mean 0, std 1); the 256 x 256 image reduced "
                                    f"by {256 // args.size}x{256 // args.size} block means")},
        "output": {"name": "logits", "shape": [1, 1, args.size, args.size],
                   "kind": "logits", "kidney_channel": 0},
        "scenario": {"segmenter": "onnx", "onnx_model": str(onnx_path),
                     "onnx_input_shape": [1, 1, args.size, args.size], "onnx_input_mean": 0.0,
                     "onnx_input_std": 1.0, "onnx_output": "logits"},
        "training": {"sources": sources, "frames_per_source": args.frames,
                     "epochs": args.epochs, "width": args.width, "lite": args.lite,
                     "train_seconds": round(time.time() - t),
                     "recipe": "drake_rus/imaging/train_segmenter.py"},
    }
    (out / "kidney_unet.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(f"wrote {onnx_path} ({onnx_path.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
