"""drake-rus benchmarks: ``python -m benchmarks NAME``; each prints one JSON object last."""
