"""The node's mapping side: the core that holds the map and its changes (``mapping_thread``),
the inputs taken in on the executor thread (``intake``), the update thread that integrates the
clouds (``update_thread``), and the SLAM's corrections applied to the map (``corrections``).
"""
