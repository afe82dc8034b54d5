"""The commands behind the top-level scripts: ``train`` (``train.py``,
``cpl-train``) and ``evaluate`` (``evaluate.py``, ``cpl-evaluate``)."""
