"""The node's outputs: the map topics sent from one publishing thread (``publisher``), the
PointCloud2 encoder (``cloud_encoding``), the costmap topic and service (``costmap``) and the
node's status and diagnostics (``status``).
"""
