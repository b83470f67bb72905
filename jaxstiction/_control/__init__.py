"""The loop under its controller: the PI identified from a record or given
(`controller`), and a fitted model closed again around it in simulation
(`closedloop`). Shared by the verdict (does the fitted valve reproduce the recorded
limit cycle?) and the what-if (what would a repair buy?)."""
