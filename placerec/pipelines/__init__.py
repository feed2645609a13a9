"""Place-recognition pipelines (registered by name in `placerec.recognizer.PIPELINES`)."""
