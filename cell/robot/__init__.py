"""The cell's robots: the datagram they speak, their model, and the emulators behind them."""
