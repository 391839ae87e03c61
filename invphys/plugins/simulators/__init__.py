"""Built-in simulator machinery: a plain Python function as a simulator (:mod:`.function`)."""
