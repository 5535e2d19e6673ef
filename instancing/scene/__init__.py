"""The built scene: typed description, instance ids and table, two-phase intersection,
camera, lights and :class:`~instancing.scene.scene.Scene`."""
