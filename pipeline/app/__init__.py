"""The commands: the command line, run, serve and bench, and the session they share."""
