"""Stand-alone monitoring web application reading the stockpile's virtual
sensors over REST (paper section "Integration test")."""
