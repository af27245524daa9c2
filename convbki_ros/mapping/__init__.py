"""The node's mapping side: the thread that takes synced clouds into the map
(``mapping_thread``) and the SLAM's corrections applied to it (``corrections``).
"""
