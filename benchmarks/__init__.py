"""The benchmark suite (`make bench`): measures, never asserts. Table on stdout, JSON to a file."""
