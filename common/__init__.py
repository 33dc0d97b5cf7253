"""The library that services, the simulator and the tools share: the bus (the only module that
imports zenoh), the service runtime, wire messages and key expressions, parameters, grid
geometry and classification, map files. It imports nothing from ``services``, ``sim`` or
``tools``."""
