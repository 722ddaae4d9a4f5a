"""Finding ArUco markers in intensity images, with corners accurate to a tenth of a pixel."""

from annotator.detection.aruco import Detection, MarkerDetector

__all__ = ["Detection", "MarkerDetector"]
