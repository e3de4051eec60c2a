"""Fixtures of the security tests: the service tests' ``daemons`` (killed at teardown)."""

from tests.service.conftest import daemons

__all__ = ["daemons"]
