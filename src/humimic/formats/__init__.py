"""File formats humimic reads and writes, beyond its own ``.npz`` motion files.

:mod:`humimic.formats.mcap`: MCAP logs (motion references, rollouts, robot logs) for Foxglove.
"""
