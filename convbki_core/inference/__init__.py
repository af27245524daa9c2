"""Bayesian kernel inference: the paper's update (Eq. 2-4).

``kernels`` builds the sparse kernel (Eq. 5) and its learned per-class lengths, ``layer`` is
the paper's dense depthwise convolution of the input volume F, ``update`` the same update as
a compiled sparse scatter into the resident window (exact to the layer), and ``statistics``
the Dirichlet mean and variance of a voxel (Eq. 2). Imports ``geometry``, ``memory`` and
``io`` (kernel files).
"""
