"""The runtime: loop runner and on-robot daemon parts."""
