"""Training on labelled drives: ``trainer`` learns the kernel's lengths on SemanticKITTI-format
sequences (the loop), from the samples of ``samples`` under the loss of ``objective``, scored on
the held-out frames of ``validation``; ``sparse_plan`` evaluates the update at chosen voxels only
(differentiable in the kernel), ``free_samples`` trains the free-space length, ``temperature``
scales a network's class probabilities and ``temperature_fit`` fits that scale on the validation
frames. Above the mapper: it maps drives to score them.
"""
