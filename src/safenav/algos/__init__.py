"""The algorithms: CSAC (the paper's method, :mod:`safenav.algos.csac`) and its SAC baseline
(:mod:`safenav.algos.sac`), their pure losses (:mod:`safenav.algos.losses`), and the loader of
trained policies (:mod:`safenav.algos.policy`)."""
