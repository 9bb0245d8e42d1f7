"""The web page: a team's run tracker, drawn on the server over the service's data.

``web`` mounts the pages (``install_web``: sign-in, the lists, a job's and a suite's pages, the Rerun web
viewer); a module per kind of page: the runs table (``runs_web``, its charts ``runs_charts``), a job
(``job_web``, a running job's view ``live_view``), comparisons (``compare_web``, their plots
``compare_plots``), a suite's history (``history_web``), the audit trail (``audit_web``), people
(``people_web``). ``pages`` is what every page shares (templates, session, error page), ``svg_plots`` the
plots drawn on the server, ``viewer_assets`` the Rerun web viewer served from the installed rerun-sdk;
``templates/`` and ``static/`` hold the page's files. It may import the service, never the command line.
"""
