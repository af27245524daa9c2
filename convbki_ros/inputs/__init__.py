"""The node's inputs: clouds decoded from PointCloud2 (``cloud_decoding``), SLAM paths read from
their serialized bytes (``path_decoding``), poses from odometry (``pose_buffer``) and TF
(``tf_buffer``), the clouds waiting for their pose (``sync``) and the stamp and pose messages
(``transforms``).
"""
