"""Files: kernel files (``kernel_file``), map files (``map_file``), PLY exports (``ply``), the
label map (``labels``: class names, colours and the dataset's label ids) and atomic writes
(``atomic``), so that nothing a user saved is ever left half written; a mapper's own map files
(``mapper_files``: the mapper's save, load and PLY export, a mixin). Imports ``memory``
(packed rows) and ``correction`` (the scan log a map file carries).
"""
