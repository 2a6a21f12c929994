"""The DETR-style BEV detector: encoder, query initialisation, decoder, heads."""

from detectors.model.bev import BEVGrid
from detectors.model.detector import Detector, DetectorConfig
from detectors.model.heads import decode_boxes, encode_boxes

__all__ = ["BEVGrid", "Detector", "DetectorConfig", "decode_boxes", "encode_boxes"]
