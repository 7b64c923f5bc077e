"""What a person watches: the web viewer and the status endpoint."""
