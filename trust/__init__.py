"""Who may say what on the mesh: member keys and the roster, signatures, the fleet
authority, roster following, station heartbeats, TLS set-up."""
