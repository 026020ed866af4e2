"""`cell fuzz`: bad input at scale against every listener of a running cell."""
