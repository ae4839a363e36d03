"""Per-pixel YUV Gaussian background model: from empty-scene frames, or estimated from a moving sequence.

See :mod:`torchtrack.background.model` for the conventions (kornia YUV, diagonal covariance, luminance
relaxation, global gain compensation, dead frames).
"""

from torchtrack.background.model import (
    FOREGROUND_MAHALANOBIS2, MIN_FRAMES, MIN_SEQUENCE_FRAMES, BackgroundConfig, BackgroundModel,
    MovingSequence, sequence_statistics,
)

__all__ = ["FOREGROUND_MAHALANOBIS2", "MIN_FRAMES", "MIN_SEQUENCE_FRAMES", "BackgroundConfig", "BackgroundModel",
           "MovingSequence", "sequence_statistics"]
