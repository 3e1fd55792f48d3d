"""The ``humimic`` command line: :mod:`.main` parses and dispatches; one module per command
group holds its dataclasses and runners, which call the library."""
