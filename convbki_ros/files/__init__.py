"""The node's files: the map loaded at start or on request and saved on request, on a timer
and at shutdown, always atomically (``map_files``).
"""
