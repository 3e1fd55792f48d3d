"""The ``humimic`` command line."""
