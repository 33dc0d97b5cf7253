"""Controller service: pure-pursuit path following with a laser safety stop."""
