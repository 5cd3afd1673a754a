"""Primitive kinds: one definition per kind, each in its own module (:mod:`.triangle`, :mod:`.bounding_box`,
...), listed in :data:`.registry.KINDS`."""
