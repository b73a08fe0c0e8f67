"""The shipped configuration (data only): ``default.toml``, ``ideal.toml``, ``worlds/*.toml`` and
``koala.dbc``. Installed as :mod:`koala_bridge.config` and read with :mod:`importlib.resources`
(:mod:`koala_bridge.core.resources`), so a wheel finds it wherever it is installed."""
