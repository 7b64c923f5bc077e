"""What a person watches: the progress bar, the web and desktop viewers and the status endpoint."""
