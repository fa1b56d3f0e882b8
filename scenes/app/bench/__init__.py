"""The detection test bench: per-source labels, their file formats, a dataset manifest and the scorer.

``labels`` computes each source's label from its noiseless stamp and the frame's noise model
(:func:`scenes.app.bench.labels.labels_from_sources`); ``frame`` gets the stamps of a render;
``formats`` writes COCO, SatNet-style JSON, YOLO-OBB and the FITS ``LABELS`` image; ``score`` matches
detections to labels and measures completeness and purity; ``inject`` draws objects into a measured frame;
``detect`` is the baseline detector (docs/detection_bench.md).
"""

from .labels import (
    MASK_FRACTION_SIGMA,
    NO_SOURCE,
    Label,
    NoiseModel,
    SourceStamp,
    dominant_source_image,
    label_rule,
    labels_from_sources,
)

__all__ = ["MASK_FRACTION_SIGMA", "NO_SOURCE", "Label", "NoiseModel", "SourceStamp", "dominant_source_image",
           "label_rule", "labels_from_sources"]
