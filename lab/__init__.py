"""The lab: what a user runs but need not read to learn the method."""
