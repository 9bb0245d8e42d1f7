"""The fuzz tests, harnesses and campaigns: a package, so that its conftest is ``fuzz.conftest``, shadowing no
other ``conftest``."""
