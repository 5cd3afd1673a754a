"""Primitive kinds: one definition per kind (:mod:`.triangle`, :mod:`.bounding_box`, :mod:`.curve`,
:mod:`.sphere`), listed in :mod:`.registry`."""
