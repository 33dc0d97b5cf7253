"""Launch profiles (``core``, pure) and the supervisor that runs them (``supervisor``)."""
