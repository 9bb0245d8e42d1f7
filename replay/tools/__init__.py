"""Tools beside a run: ``inspect`` (a recording's health and topics), ``navigate`` (topo-metric navigation on a
saved map) with ``topomap_io``, ``graph_io`` (pose-graph files), ``snapshot`` (a run drawn by the Rerun viewer
to PNG), ``sources`` (the Victoria Park importer, here because its reference map comes from evaluation) and
``codeprint`` (the code version a result was made with). They may import the engine and evaluation.
"""
