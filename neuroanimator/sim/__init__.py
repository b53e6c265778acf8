"""MuJoCo models as data: reading what users ship (``bundle``), compiling it where MuJoCo can read
nothing else (``sandbox``, ``landlock``), and the errors they raise (``errors``). Light to import: the
sandbox's processes start from here without the catalog."""
