"""Tests of tofcore (a package: tests/batch has modules of the same names)."""
