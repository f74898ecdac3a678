"""The cloud-edge link: robots (edge) far from the trainer (cloud), over one authenticated,
encrypted connection the edge dials out (docs/edge.md)."""
