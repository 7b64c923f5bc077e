"""One module per command: its arguments (`add_arguments`) and its `run`, which imports what the
command needs only when it runs (--help stays fast)."""
