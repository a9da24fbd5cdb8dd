"""The sensor model: one physics description that is both simulated and fitted.

``model.SensorModel`` is the value (offset, soft iron, field, noise, quantum, offset wander,
channel terms, temperature gain, glitches, direction nonlinearity, saturation); ``wander`` the
stochastic offset process; ``directions`` the degree-3/4 direction basis; ``physics`` the
simulated board (motion, environment, the AK8975's registers) that draws from the model.
"""
