"""The debris-detection test bench: objects injected into measured frames (:mod:`.inject`) and a baseline
detector (:mod:`.detect`); docs/detection_bench.md."""
