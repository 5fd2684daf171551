"""Offline tools of the learned segmenter, apart from the imaging runtime: the training data
(emulated frames of generated patients, domain randomisation), the trainer, the int8
quantizer and the held-out evaluation. Nothing in a scan imports this package; the model the
scan runs is an ONNX file in models/segmenter/ (docs/imaging.md)."""
