"""The supervisor: watches the whole fleet, checks safety live and writes the summary."""
