"""What fixing the valve would buy: the loop closed again in simulation with the
identified controller, process and disturbance (`whatif`), a compensator until the
repair (`compensate`), and a valve's trend across recordings (`trend`)."""
