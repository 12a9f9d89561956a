"""Depth-sequence readers. ``open_sequence`` auto-detects the format; see base.py for the interface."""

from .base import BadFrameReport, DatasetError, DepthSequence, FrameError, GroundTruth

__all__ = ["BadFrameReport", "DatasetError", "DepthSequence", "FrameError", "GroundTruth"]
