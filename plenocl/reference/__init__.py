"""Plain NumPy references for every kernel, written for clarity rather than speed.

Tests compare each OpenCL kernel against its twin here.
"""

from . import reconstruct
from .simulate import random_words, trace_particles, trace_white

__all__ = ["reconstruct", "random_words", "trace_particles", "trace_white"]
