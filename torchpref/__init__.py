"""torchpref."""
