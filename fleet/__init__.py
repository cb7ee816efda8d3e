"""Fleet level: scenario files, programmatic scenes, and the tools that run them."""
