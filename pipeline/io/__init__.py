"""Everything that talks to the outside world: datasets, streams and files."""
