"""The command-line programs (``evaluate``, ``train``, ``synth``, ``label_noise``, ``bench``,
``map_tool``, ``warm_up``, the soak study): thin front ends over the method and its measures.
"""
