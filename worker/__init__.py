"""Worker side of dst-service: the pure geometry core (``worker.dst``) and, later, the job runner."""
