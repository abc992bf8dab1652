"""Experiments: the evaluation protocol (paper IV-B), multi-seed sweeps on Ray, figures."""
