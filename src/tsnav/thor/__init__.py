"""AI2-THOR interchange: ``tsnav thor`` imports the lineage's offline data and exports tsnav worlds in its layout."""
