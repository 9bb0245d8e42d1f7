"""The doors: the command line, the HTTP service, the web page and the Python client, over ``replay``.

Four rooms, each a sub-package saying what it owns, and the rule of which may import which
(``tests/test_layers.py``):

- ``cli``: the ``slamreplay`` command, a module per command group, each registering its own parser
  (``main`` builds the parser and dispatches). It imports the service only to start it (``serve``), to
  manage people in its store (``users``) and for the executors a local suite run shares with it.
- ``service``: the HTTP API: settings, the job store, the executors that run jobs in worker processes or
  on Ray, guards and limits, and a router per resource (recordings, jobs, suites, history, live
  recordings, pushed runs, the audit trail). It imports neither the web page nor the command line.
- ``web``: the web page (a team's run tracker): a module per kind of page, the templates, static files
  and the plots drawn on the server. It may import the service.
- ``client``: a Python client of the service (standard library only), as ``slamreplay push`` uses it.

``app`` sits above the rooms: ``create_app`` builds the service and mounts the web page on it.
"""
