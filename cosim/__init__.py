"""MineTwin core: particles, size classes, block model, events, sensors,
storage models, the FMU co-simulation master, scenarios, analyses and the CLI.

See docs/architecture.md and the paper "Digital twins with distributed particle
simulation for mine-to-mill material tracking" (Servin, Vesterlund, Wallin).
"""

__version__ = "0.1.0"
