"""The simulator: a pymunk differential-drive robot with a 2-D laser (``core``), worlds and their
files (``world``, built-in worlds in ``worlds/``) and the simulator process (``service``)."""
