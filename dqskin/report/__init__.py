"""Side-by-side skinning reports: :mod:`.compare` (``dqskin compare``: skin, measure, render,
write),
:mod:`.render` (the offscreen Warp ray caster and image helpers, Pillow), :mod:`.html` (the
self-contained page, matplotlib plots), :mod:`.defaults` (its defaults and limits, light: the
command line's parser reads them)."""
