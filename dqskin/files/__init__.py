"""File machinery the readers and writers share, free of any format's reader or writer.

:mod:`.inputs` (the one check where any input is opened: regular files only, ``.npz`` arrays
sized before they are read), :mod:`.atomic` (every output appears complete under its final name,
or not at all; interrupts deferred while a file is claimed or committed), :mod:`.direct` (files
appended past the page cache) and :mod:`.crate` (time samples streamed into a USD crate file
without an Sdf layer). Importing this package imports none of them.
"""
