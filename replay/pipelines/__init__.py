"""Built-in pipelines. Each is found through its entry point in group ``slamreplay.pipelines``
(pyproject.toml), the same way as a user's plugin: importing this package registers nothing."""
