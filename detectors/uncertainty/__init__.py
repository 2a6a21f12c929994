"""Covariance sources for a detection's box: spread across decoder layers, attention spread."""

from detectors.uncertainty.attention_spread import AttentionSpread, attention_spread
from detectors.uncertainty.layer_spread import layer_covariance

__all__ = ["AttentionSpread", "attention_spread", "layer_covariance"]
