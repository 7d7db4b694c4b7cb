"""cosim: headless co-simulation data generator for drone-assisted V2X collaborative perception."""

__version__ = "0.1.0"
