"""Scene and file I/O: scene files, Mitsuba XML in and out, triangle meshes, images."""
