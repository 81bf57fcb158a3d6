"""Mock ABB 800xA-style process simulator served over OPC UA (asyncua):
conveyors with bins, the stockpile discharge setpoint, loss-free tracking
exchange (paper section "Integration test")."""
