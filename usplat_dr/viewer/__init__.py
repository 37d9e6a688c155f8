"""The interactive viewer behind ``usplat view``: ``scene`` (cameras, views, the scenes that
render them) and ``server`` (the viser server and its render queue)."""
