"""InfiniRL: RL infrastructure for post-training foundation models and robot policies.

The layers (docs/architecture.md): ``runtime`` (distributed core), ``engines`` (compute backends),
``algorithms`` (pure tensor functions), ``components`` (RL workers), ``runners`` (macro flows).
"""

__version__ = "0.1.0"
