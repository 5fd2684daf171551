"""Scenario section ``imaging``: probe fan geometry, sensor rate, emulator and segmenter.

Units are SI (m, s) unless the field name says otherwise (``_deg``, ``_hz``, ``_mhz``,
``_db``). Probe and tissue numbers come from ``docs/facts/anatomy_and_ultrasound.md``.
"""

from dataclasses import dataclass, field

from drake_rus.config_schema import physical


@dataclass
class ImagingConfig:
    # Frame rate of the slice sensor / frame grabber (Hz). The seed grabbed frames at 20 fps.
    frame_rate_hz: float = field(
        default=20.0,
        metadata=physical(1.0, 200.0, "Hz", "ultrasound frame rates are 10-100 Hz", positive=True),
    )

    # --- Curvilinear probe (like the seed's GE C1-6; facts: "Probe") -----------------------
    # Radius of curvature of the transducer face (m). Comparable convex probes: 45-60 mm.
    probe_radius: float = field(
        default=0.050,
        metadata=physical(
            0.005, 0.2, "m", "convex probe faces are 10-80 mm in radius", positive=True
        ),
    )
    # Full opening angle of the fan (deg). Comparable probes span 56-73 deg, but the seed
    # quotes "around 10 cm lateral width at 10 cm depth" for its images, which with a 50 mm
    # radius is a 40 deg fan (2 * 150 mm * sin 20 deg = 103 mm); we follow the seed.
    field_of_view_deg: float = field(default=40.0, metadata={"positive": True, "max": 170.0})
    # Imaging depth from the probe face along each scan line (m). Kidney lies 80-105 mm deep
    # in most generated bodies; real bodies go deeper (147.5 mm in the VH female, supine).
    depth: float = field(
        default=0.150,
        metadata=physical(0.03, 0.4, "m", "curvilinear probes image 30-300 mm deep", positive=True),
    )
    # The probe's depth presets (m): the start planner picks the shallowest that holds the
    # whole kidney, and ``depth`` follows it. Curvilinear abdominal probes offer presets up
    # to about 240-300 mm (docs/facts/anatomy_and_ultrasound.md, "Probe").
    depth_presets: list[float] = field(
        default_factory=lambda: [0.10, 0.15, 0.20, 0.25, 0.30],
        metadata=physical(0.03, 0.4, "m", "curvilinear probes image 30-300 mm deep", positive=True),
    )
    # Elevational (slice) beam width (m): comparable probes 7-14 mm.
    elevation_width: float = field(
        default=0.010,
        metadata=physical(0.0005, 0.05, "m", "elevational beam widths are a few mm", positive=True),
    )
    # Number of parallel planes sampled across the elevational width (1 = a thin plane).
    elevation_planes: int = field(default=1, metadata={"min": 1, "max": 15})
    # How the planes' labels combine per pixel: "majority" (most frequent label) or "max"
    # (the highest label value, which favours gas and bone: elevational shadowing).
    elevation_combine: str = field(default="majority", metadata={"choices": ["majority", "max"]})
    # Size of the scan-converted (Cartesian) image in pixels: rows (depth), columns (lateral).
    image_height_px: int = field(default=256, metadata={"min": 16, "max": 4096})
    image_width_px: int = field(default=256, metadata={"min": 16, "max": 4096})

    # --- Ultrasound emulator -----------------------------------------------------------------
    # Number of scan lines across the fan and samples along each line (the beamformed grid).
    scan_lines: int = field(default=128, metadata={"min": 8, "max": 2048})
    samples_per_line: int = field(default=256, metadata={"min": 16, "max": 4096})
    # Centre frequency (MHz): C1-6 band about 1.8-5 MHz.
    center_frequency_mhz: float = field(
        default=3.5, metadata=physical(0.5, 20.0, "MHz", "diagnostic ultrasound", positive=True)
    )
    # Time-gain compensation (dB/cm/MHz, two-way applied as 2x): compensates average soft
    # tissue attenuation (about 0.5-1.0 dB/cm/MHz in the facts table).
    tgc_db_per_cm_mhz: float = field(default=0.7, metadata={"min": 0.0})
    # Log-compression dynamic range (dB) and overall gain (dB).
    dynamic_range_db: float = field(default=50.0, metadata={"positive": True})
    gain_db: float = field(default=-12.0)
    # Speckle: multiplicative Rayleigh amplitude (0 = no speckle).
    speckle: bool = True
    # Gain of the specular echo at tissue interfaces (relative to the reflected intensity).
    interface_gain: float = field(default=6.0, metadata={"min": 0.0})
    # Air within this distance of the face, before any tissue on a scan line, counts as
    # coupling gel (m): the convex face's corners sit 3 mm above its centre.
    gel_gap: float = field(default=0.005, metadata={"min": 0.0})

    # --- Segmenter -----------------------------------------------------------------------------
    # "onnx": a learned model through ONNX Runtime on the grey image (ours ships in
    #   models/segmenter/: mean IoU about 0.9 on held-out patients' emulated frames);
    # "oracle": kidney labels of the ground-truth label image (like the seed's simulation; the
    #   Segmenter then reads the station's label_image, for controller studies);
    # "classical": filtering + thresholding + morphology on the grey image (weak).
    segmenter: str = field(default="onnx", metadata={"choices": ["oracle", "classical", "onnx"]})
    # Minimum kidney area (m^2) for the kidney to count as visible (rejects specks).
    min_kidney_area: float = field(default=1.0e-4, metadata={"min": 0.0})
    # ONNX model file: absolute, or relative to the repository root. The default is the int8
    # quantization of our fp32 model (drake_rus/imaging/training/quantize_segmenter.py): 0.84
    # instead of 1.42 ms per frame (one thread, AVX512-VNNI), the same held-out IoU within
    # 0.002. On
    # an x86 CPU without VNNI its uint8 x int8 products may saturate: measured on an AVX2 AMD
    # EPYC, IoU up to 0.011 under the fp32 master "models/segmenter/kidney_unet.onnx", which
    # the segmenter's one-line warning then names (docs/imaging.md).
    onnx_model: str = "models/segmenter/kidney_unet_int8.onnx"
    # Model input shape (N, C, H, W); N may be 1. The grey image (0-255) is resized to H x W,
    # scaled to [0, 1], then normalised as (x - mean) / std, and repeated over C channels.
    onnx_input_shape: list[int] = field(
        default_factory=lambda: [1, 1, 64, 64], metadata={"length": 4, "positive": True}
    )
    onnx_input_mean: float = 0.0
    onnx_input_std: float = field(default=1.0, metadata={"positive": True})
    # What the model outputs: "logits" (sigmoid applied here), "probability" (in [0, 1]) or
    # "labels" (argmax over channels == onnx_kidney_channel).
    onnx_output: str = field(
        default="logits", metadata={"choices": ["logits", "probability", "labels"]}
    )
    # Which output channel is the kidney (for multi-channel outputs).
    onnx_kidney_channel: int = field(default=0, metadata={"min": 0})
    # Threshold on the kidney probability.
    onnx_threshold: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    # The kidney probability at which a region's edge is drawn on the image grid (onnx
    # backend; after the guided filter), the region itself being found at onnx_threshold:
    # below it, the mask reaches further out where the model is unsure (a fat-free cortex
    # against soft tissue, where the shipped model draws the kidney a canvas pixel too
    # small), without new regions. 0: onnx_threshold's value (one level for both). On the
    # validation split 0.45 gained 0.008-0.010 IoU on imported-like kidneys at every
    # preset and lost at most 0.0008 on generated ones, but marked one more kidney-free
    # frame at 250 mm, so it failed the rule fixed before scoring; lower values lost
    # 0.004-0.03 on generated kidneys (docs/results/segmenter.md).
    onnx_edge_threshold: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    # Test-time augmentation (onnx backend): average the kidney probability of the frame and
    # of its lateral mirror (onnx_backend.mirror_average; a curvilinear fan is symmetric
    # about its axis). Two model runs per frame (1.8 times the segment call's time). Off:
    # on the validation split (benchmarks/segmenter_inference.py) it gained 0.001-0.003 IoU
    # at 200-300 mm on generated patients, lost 0.001-0.004 at 100 mm, and had fewer false
    # positives (docs/results/segmenter.md). The threshold above, 0.35 instead of 0.5,
    # gained on imported-like kidneys (VH female 0.816 / 0.846 instead of 0.803 / 0.831)
    # and lost 0.002-0.004 at every preset on the generated test patients: 0.5 stays.
    onnx_mirror_average: bool = False
    # A second ONNX model (path as onnx_model; "" for none) whose kidney probability is
    # averaged with onnx_model's, pixel by pixel on the model grid, before the guided filter
    # and the threshold (onnx_backend.ensemble_average; with onnx_mirror_average each model
    # runs on the frame and on its mirror). It takes the same input and output fields
    # (onnx_input_*, onnx_output, onnx_kidney_channel) and its card must declare the same
    # canvas as onnx_model's. One more model run per frame. Off: with the boundary-band
    # candidate as second model, on validation patients neither model saw, neither the
    # ensemble nor ensemble + mirror passed the rule fixed before scoring (ensemble + mirror
    # gained at every generated preset but lost 0.004 IoU on imported-like kidneys at
    # 100 mm; docs/results/segmenter.md).
    onnx_ensemble_model: str = ""
    # Candidate kidney regions smaller than this (m^2) are dropped before the largest or the
    # tracked one is chosen (onnx_backend.drop_small_regions); 0 keeps every region. On the
    # validation split 0.5-1 cm^2 changed nothing and 2 cm^2 cost 0.028 IoU at 100 mm (a
    # pole's small sections are kidney).
    onnx_min_region_area: float = field(
        default=0.0, metadata=physical(0.0, 0.01, "m^2", "a kidney section is 5-60 cm^2")
    )
    # The mask's boundary at the image's resolution (onnx backend): the kidney probability,
    # mapped back from the model's grid (2.4 mm canvas pixels), is refined by a guided filter
    # with the frame's grey as guide (onnx_backend.guided_filter: a local linear fit of the
    # probability to the grey in windows of this radius, m, per image axis) before it is
    # thresholded, so the edge follows the image's own (the kidney's capsule) within a canvas
    # pixel. 0 turns it off. eps (grey in [0, 1], squared) is the fit's regularisation: how
    # much grey contrast a window needs before the probability follows it. Chosen on the
    # validation split and measured once on the test split (docs/results/segmenter.md,
    # "the mask's boundary"): 1.5 mm and 0.01 gained 0.003-0.005 IoU at every preset
    # (100 mm 0.862 instead of 0.859), the VH female 0.804 / 0.831 (0.803 / 0.831), the
    # same false positives, for 1.4 times the segment call's time (about 0.3 ms a frame).
    onnx_guided_radius: float = field(
        default=0.0015,
        metadata=physical(
            0.0, 0.01, "m", "a canvas pixel is 2.4 mm; windows beyond 5 mm blur the kidney"
        ),
    )
    onnx_guided_eps: float = field(
        default=0.01,
        metadata=physical(
            1e-6, 1.0, "(grey/255)^2", "the frame's grey variance in a window is 0-0.25"
        ),
    )
    # Following the kidney from frame to frame (onnx backend): the model may also mark a
    # hypoechoic region that is not the kidney (a muscle band, a bowel loop). Once the kidney
    # is seen, a frame's kidney is the candidate region overlapping the last kidney mask grown
    # by ``track_reach`` (m), and for ``track_gap`` s after the kidney was last seen a region
    # elsewhere is not taken for it (at 20 frames/s a kidney section moves millimetres between
    # frames; it does not jump across the image). After the gap, the largest region is taken.
    # 2 s spans a pivot leg's reversal: the kidney leaves the image at a pole, the probe turns
    # back and the kidney re-enters where it left. Measured on the VH female in left lateral
    # decubitus (the muscle band under the kidney marked in 5 of 30 late pivot frames): with
    # 0.5 s the band was taken for the kidney during the reversal and the tracking check
    # stopped a good scan; with 2 s the scan ended DONE.
    track_gap: float = field(default=2.0, metadata={"min": 0.0})
    track_reach: float = field(default=0.010, metadata={"min": 0.0})
    # ... and at least this fraction of the region must lie in the grown mask, or the region
    # must cover at least this fraction of the last mask itself: a region that merely
    # touches the grown mask is not the kidney. Measured (test:0 supine, test:1 decubitus,
    # seed 5,000,007 decubitus; 3,100 followed frames): a kidney section continuing the last
    # one has 0.93-1.00 of its area there; a hypoechoic region at the image's top edge that
    # touched the grown mask at a pivot leg's end had 0.012 and covered none of the last
    # mask, and following it hid the kidney on the way back (segmentation lost, a safety
    # stop). A kidney re-entering the image after a pivot leg's end (seed 5,000,009 supine)
    # has only 0.13-0.30 of its area within reach of its last small section, but covers
    # 0.74-1.00 of that section within 0.2 s.
    track_min_overlap: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    # The kidney is followed only once it has been seen without a jump for ``track_confirm``
    # s; before, each frame takes its largest region. While the probe lands, the first
    # frames may show a region that is not the kidney (measured on the VH female, supine:
    # a region taken in the first frame and followed hid the kidney for the whole
    # exploration).
    track_confirm: float = field(default=0.5, metadata={"min": 0.0})
    # After localization the registered template predicts the kidney's section in every
    # frame (segment.predicted_section; the Segmenter's ``kidney_surface`` input): a region
    # with at least ``track_min_overlap`` of its area within that section grown by this
    # distance (m) agrees with the template, and is taken for the kidney even when it does
    # not continue the last mask (the kidney found again after a pivot leg's end or any
    # loss). 15 mm: the registration's error on the generated and real bodies is 0.3-4.4
    # mm across the long axis (docs/results), and the template's length differs from the
    # kidney's by up to 16 mm along it (localization/tracking.py), half of it at each pole.
    track_section_reach: float = field(
        default=0.015,
        metadata=physical(0.0, 0.1, "m", "registration errors are millimetres"),
    )
    # Acoustic shadow (segment.acoustic_shadow): a pixel is shadowed when its scan line's
    # grey, averaged over 4 mm of depth, stays below this fraction of the lit fan's median
    # grey from the pixel's depth down (bone and gas leave their lines dark; the emulator's
    # shadows are black, a real machine's dim to 0-25% of the tissue's grey: the training's
    # synthetic shadows). A kidney mask's outline in a shadow is drawn, not seen: its
    # boundary pixels there do not feed the point cloud nor the kidney tracking
    # (segment.echo_supported_boundary). 0 switches the rule off.
    shadow_floor: float = field(default=0.3, metadata={"min": 0.0, "max": 1.0})
    # A frame whose kidney mask lies more than this fraction in shadow gives no boundary
    # pixels at all (its controller read-outs are kept: the kidney goes on under a rib).
    # Measured on seed 5,000,002 decubitus: the masks drawn in a rib's shadow lay 0.57-1.00
    # in it (48 frames); a kidney partly under the shadow, seen beside it, 0.06-0.31.
    shadow_max_fraction: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    # The exploration cloud leaves out a frame whose section (the extent in B of its
    # boundary points) lies more than this distance (m) from the median of the last 5
    # frames' sections on any side (backprojection.accumulate_consistent): between frames a
    # fraction of a millimetre apart a kidney's section moves millimetres (about 3 mm at a
    # pole), a mask leaking into a neighbour or drawn where the image shows nothing jumps
    # further. 0 switches the check off.
    cloud_section_jump: float = field(
        default=0.010,
        metadata=physical(0.0, 0.1, "m", "a section moves millimetres between frames"),
    )
    # ONNX Runtime intra-op threads (1 leaves the other cores to the simulation).
    onnx_threads: int = field(default=1, metadata={"min": 1, "max": 64})
