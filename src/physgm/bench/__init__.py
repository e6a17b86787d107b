"""Benchmark suites. Each is a program that prints one JSON object; none gates CI."""
