"""The pipeline services, one package each: a pure ``core`` (no I/O, no clock, no zenoh) and a
thin ``service`` shell that decodes, calls the core, encodes and publishes."""
