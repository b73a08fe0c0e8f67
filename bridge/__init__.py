"""koala-bridge: a hardware-in-the-loop bridge for the K-Team Koala.

The import package ``koala_bridge`` is this folder (``bridge/``); the repository's other code
folders are its subpackages: ``drivers/`` is :mod:`koala_bridge.drivers`, ``sim/`` is
:mod:`koala_bridge.sim`, and ``config/`` (data only) is :mod:`koala_bridge.config`
(docs/architecture.md, "Folders and import names"). Importing this package has no side effects.
"""

__version__ = "0.2.0"
