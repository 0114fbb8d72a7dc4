namespace tether {}
