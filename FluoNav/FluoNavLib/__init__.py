"""Navigation: ray casting, illumination model, surface flux, live devices."""
