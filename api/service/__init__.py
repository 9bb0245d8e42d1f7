"""The HTTP service: the API over the job store, and what runs and guards it.

``app`` builds the service (``create_service``: settings, the store, an executor, the middleware and a
router per resource: ``recording_routes``, ``job_routes``, ``record_routes``, ``live_routes``,
``suites_routes``, ``history_routes``, ``audit``, ``push``); the services the routes delegate to
(``recordings``, ``jobs``, ``suites``, ``compare_runs``; the runs query and its grammar and groups:
``runs_query``, ``runs_grammar``, ``runs_groups``); the store (``store``, ``store_runs``, ``people``,
``storage``, ``datalock``); the executors (``executor``, ``ray_executor``, ``limits``); people and
sessions (``auth``); guards (``siteguard``, ``timeouts``, ``multipart``, ``idprefix``, ``submit_checks``);
``settings``, ``models``, ``errors``, ``ids``, ``deps``, ``monitoring`` and the offline API docs
(``docs_pages``). It imports neither the web page nor the command line (``tests/test_layers.py``).
"""
