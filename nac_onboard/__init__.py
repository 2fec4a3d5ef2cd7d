"""Companion-computer software: MAVLink client, agent, flight logs, link model, MPI compute."""
