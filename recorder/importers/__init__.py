"""Importers that turn public datasets into slamreplay recordings."""

from slamreplay.recorder.importers.mrclam import ImportSummary, import_mrclam

__all__ = ["ImportSummary", "import_mrclam"]
