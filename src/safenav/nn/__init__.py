"""Networks shared by all algorithms: ensemble layers, feature extractors, actor and critics.

- :mod:`safenav.nn.config` - :class:`~safenav.nn.config.NetConfig` (sizes, extractor sharing).
- :mod:`safenav.nn.layers` - ensemble linear/MLP layers and the circular range-image convolution.
- :mod:`safenav.nn.extractors` - the SafeNav extractor (CNN + MLP + state) and the flatten one.
- :mod:`safenav.nn.networks` - the squashed-Gaussian actor, the critic ensemble, the deployable
  deterministic actor, and how gradients flow through the extractor(s).

Nothing is imported here, so that importing :mod:`safenav.nn.config` does not import torch.
"""
