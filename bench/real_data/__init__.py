"""Converters from public raw sensor logs to measurement bundles (docs/bundle-format.md).

Each ``convert_<name>.py`` reads the upstream files from a fetched snapshot of the source
repository (a bare git directory, read with ``git show COMMIT:PATH``, pinned to the commit named
in the bundle's ``meta.json``) and writes ``tests/data/real/<name>/``. Run one with
``python -m bench.real_data.convert_<name> [--mirror DIR] [--out DIR]``, or all with
``python -m bench.real_data``.
"""
