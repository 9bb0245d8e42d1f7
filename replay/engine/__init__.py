"""The engine: a recording read message by message (``reader``, ``recording_file``) and stepped through one
pipeline in replay order (``loop``), with what the pipeline shows logged to Rerun (``observer``, ``views``)
and its trajectory kept (``trajectory``). ``pipeline`` is the plugin contract: the ``Pipeline`` base class,
config layers, and the registry of pipelines found through entry points.

The engine produces; it does not judge: it imports neither ``evaluation`` nor ``runs`` (tests/test_layers.py).
"""
