"""The operator's limits as the code checks them: the H2's joints (angles, step, torque caps) and
the MACCEPA boards' (set-point, duty, gains)."""
