"""lcrl: the learning core (frozen text encoder, goal spaces, replay, learners)."""

from lcrl.errors import LcrlError

__all__ = ["LcrlError"]
__version__ = "0.1.0"
