"""One panel per module; each takes its model(s) and never reaches into another panel."""
