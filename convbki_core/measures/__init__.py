"""How a map is judged: mIoU and confusion (``metrics``), calibration of the variance
(``uncertainty``), the trails that moving objects leave (``trails``), the costmap against the
ground truth (``costmap_eval``) and a corrected map against one built from scratch
(``correction_eval``). The highest stage: it may import every stage below it, and nothing in
the mapper imports it.
"""
