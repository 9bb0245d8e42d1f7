"""A Python client of the service (standard library only): ``Client`` uploads recordings, submits and lists
jobs, and pushes runs made elsewhere; ``slamreplay push`` is built on it."""

from slamreplay.api.client.client import Client, ClientError

__all__ = ["Client", "ClientError"]
