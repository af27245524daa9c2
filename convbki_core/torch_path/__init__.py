"""The torch path: the whole window kept on a torch device (a GPU; the CPU in tests).

``window.TorchWindow`` is the resident window's twin on the device: the update, free space,
the movers' rules and the outputs' records run there, and only slabs that leave the window
and the records asked for cross to the host. Imports the stages below it (``geometry``,
``memory``, ``inference``, ``free_space``, ``outputs``).
"""
