"""Primitive kinds: one definition per kind (:mod:`.triangle`, :mod:`.bounding_box`, :mod:`.curve`), listed
in :mod:`.registry`."""
