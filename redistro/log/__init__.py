"""The session log: every cycle recorded into MCAP, read back, summarized, plotted, exported."""
