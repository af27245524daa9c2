"""Training on labelled drives: ``trainer`` learns the kernel's lengths on SemanticKITTI-format
sequences, ``sparse_plan`` evaluates the update at chosen voxels only (differentiable in the
kernel), ``free_samples`` trains the free-space length and ``temperature`` scales a network's
class probabilities. Above the mapper: it maps drives to score them.
"""
