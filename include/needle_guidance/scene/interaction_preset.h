// Calibrated needle–tissue interaction presets (config/interaction/NAME.yaml): the needle keys a
// scene's `needle: {interaction: NAME}` defaults to, fitted to measured insertion forces.
#pragma once

#include <string>

#include "needle_guidance/scene/scene.h"

namespace needle_guidance::scene {

/// Path of the preset NAME: config/interaction/NAME.yaml.
std::string interactionPresetPath(const std::string& name);

/// The preset file a name or path stands for: a path (containing '/' or ending in .yaml) as
/// given, a name as interactionPresetPath(name).
std::string interactionPresetFile(const std::string& name_or_path);

/// The needle keys (cutting_force, cut_length, static_friction, kinetic_friction,
/// stick_velocity, diameter) of a preset, by name or by path (containing '/' or ending in
/// .yaml); absent keys and the other Needle fields stay zero. Throws SceneError naming the file.
Needle loadInteractionPreset(const std::string& name_or_path);

}  // namespace needle_guidance::scene
