"""Reading loop records (CSV, `.mat`, DataFrames, mappings) and nominal-model files.

`columns` (the column matching that both readers share) ← `read_mat` ← `read`;
`nominal` reads and writes the nominal-model JSON. Host-side NumPy only.
"""
