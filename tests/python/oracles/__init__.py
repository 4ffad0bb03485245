"""Test oracles: reference arithmetic the tests hold the package to."""
