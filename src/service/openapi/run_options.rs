//! The JSON Schema of the run options a simulation request may set (the keys of
//! `lungmotion run --config` that make sense per job), with each default filled in from
//! [`RunConfig::default`] so that the document shows what a key left out means.
//!
//! Written by hand because the configuration types live in the library, which has no
//! OpenAPI dependency; a test walks [`RunConfig`]'s serialised keys and this schema both
//! ways, so a key added to one and not the other fails the build's tests.

use serde_json::{json, Value};

use crate::run::RunConfig;

/// Keys of the run configuration a request does not set through the options: the trace
/// options sit in the request's `trace` object, and the series was chosen at upload.
pub const NOT_OPTIONS: [&str; 2] = ["trace", "series"];

/// The `RunOptions` schema, defaults included.
pub fn schema() -> Value {
    let mut schema = without_defaults();
    if let Ok(defaults) = serde_json::to_value(RunConfig::default()) {
        fill_defaults(&mut schema, &defaults);
    }
    schema
}

/// Sets `default` on every property of `schema` (recursively) from `defaults`.
fn fill_defaults(schema: &mut Value, defaults: &Value) {
    let Some(properties) = schema.get_mut("properties").and_then(Value::as_object_mut) else {
        return;
    };
    for (key, property) in properties.iter_mut() {
        let Some(default) = defaults.get(key) else {
            continue;
        };
        if property.get("properties").is_some() && default.is_object() {
            fill_defaults(property, default);
        } else if let Some(object) = property.as_object_mut() {
            object.insert("default".into(), default.clone());
        }
    }
}

fn number(description: &str) -> Value {
    json!({"type": "number", "description": description})
}

fn boolean(description: &str) -> Value {
    json!({"type": "boolean", "description": description})
}

/// One variant of a choice tagged by `kind`, with its own fields.
fn variant(kind: &str, description: &str, fields: Value) -> Value {
    let mut properties = json!({"kind": {"const": kind}});
    let mut required = vec![json!("kind")];
    if let (Some(all), Some(own)) = (properties.as_object_mut(), fields.as_object()) {
        for (name, field) in own {
            all.insert(name.clone(), field.clone());
            // A field that may be null may be left out.
            let nullable = field
                .get("type")
                .and_then(Value::as_array)
                .is_some_and(|t| t.contains(&json!("null")));
            if !nullable {
                required.push(json!(name));
            }
        }
    }
    json!({
        "type": "object",
        "description": description,
        "required": required,
        "properties": properties,
        "additionalProperties": false
    })
}

fn instants() -> Value {
    json!({
        "description": "Which instants of the trace get a displacement field (default: 10 \
            phases of the first complete cycle; a trace holding one breath is taken as one \
            period, end-exhale to end-exhale; a trace without a complete breath gets every \
            sample, said in the summary's output_instants_note)",
        "oneOf": [
            variant("every_sample", "Every sample of the trace", json!({})),
            variant("every_kth", "Every k-th sample, starting with the first", json!({
                "k": {"type": "integer", "minimum": 1, "description": "Stride in samples"}
            })),
            variant("frame_rate", "A fixed frame rate from the first sample to the last", json!({
                "hz": {"type": "number", "exclusiveMinimum": 0,
                       "description": "Frames per second (at most 100 000 frames per run)"}
            })),
            variant("phases", "`count` equally spaced phases of the first complete cycle, \
                phase 0 at end-inhale; each frame's phase in its phase_percent", json!({
                "count": {"type": "integer", "minimum": 1,
                          "description": "Number of phases (10 like a 4D-CT)"}
            })),
        ]
    })
}

fn driver() -> Value {
    json!({
        "description": "How the breathing curve becomes surface pressure",
        "oneOf": [
            variant("volume", "The pressure that makes the simulated volume equal the \
                trace's (default)", json!({})),
            variant("compliance", "ΔP = ΔV / C, the thesis's driver, or the pressure read \
                from a pressure–volume table (a non-linear compliance)", json!({
                "compliance_ml_per_pa": {"type": ["number", "null"], "exclusiveMinimum": 0,
                    "description": "Lung compliance, mL/Pa; absent (and no pressure_volume): \
                        from E, ν and the rest volume"},
                "pressure_volume": {"type": ["array", "null"],
                    "minItems": crate::motion::compliance::MIN_PRESSURE_VOLUME_ROWS,
                    "maxItems": crate::motion::compliance::MAX_PRESSURE_VOLUME_ROWS,
                    "items": {"type": "array", "minItems": 2, "maxItems": 2,
                              "items": {"type": "number"}},
                    "description": "Instead of compliance_ml_per_pa: rows [pressure Pa, \
                        volume mL], the distending (transpulmonary) pressure change from the \
                        scan and the lung volume change it gives, both strictly rising, \
                        through [0, 0], interpolated piecewise-linearly; every frame's volume \
                        must lie within the table (not extrapolated)"}
            })),
        ]
    })
}

fn dynamic() -> Value {
    json!({
        "description": "Dynamic mode (bellows law P = V/C + R·dV/dt + I·d²V/dt², explicit \
            integration) instead of quasi-static frames; null (default) for quasi-static",
        "type": ["object", "null"],
        "additionalProperties": false,
        "properties": {
            "compliance_ml_per_pa": {"type": ["number", "null"], "description":
                "Compliance C, mL/Pa; absent: measured on the model at the largest volume"},
            "resistance_pa_s_per_ml": number("Airway resistance R, Pa·s/mL"),
            "inertance_pa_s2_per_ml": number("Inertance I, Pa·s²/mL"),
            "voigt_damping_ratio": number("Voigt damping of every spring, fraction of critical"),
            "surface_damping_ratio": {"type": ["number", "null"], "minimum": 0, "description":
                "Voigt damping of the springs of elements on the lung's surface, fraction of \
                critical; absent: as the interior's (a lightly damped skin over a viscous \
                parenchyma, Boux de Casson)"}
        }
    })
}

fn tissue() -> Value {
    json!({
        "type": "object",
        "description": "How the lung's tissue varies from element to element: stiffness and \
            density from the CT's Hounsfield units (E ∝ φⁿ, φ = 1 + HU/1000 the tissue \
            fraction, the median element at the material's E), and a target stiffer than the \
            parenchyma",
        "additionalProperties": false,
        "properties": {
            "from_ct": boolean("Each element's Young's modulus and density from the CT"),
            "stiffness_exponent": {"type": "number", "minimum": 0, "maximum": 4,
                "description": "n of E ∝ φⁿ (2: open-cell foam, Gibson & Ashby)"},
            "max_stiffness_ratio": {"type": "number", "minimum": 1, "maximum": 1000,
                "description": "Clamp of an element's modulus (and density) ratio to the \
                    material's, either way"},
            "stiffness_step": {"type": "number", "minimum": 0.001, "maximum": 0.5,
                "description": "Relative step the ratios are rounded to (one element class \
                    per step)"},
            "target_stiffness_ratio": {"type": "number", "exclusiveMinimum": 0, "maximum": 1000,
                "description": "The request's target this many times the material's modulus \
                    (needs a target)"},
            "hu_to_youngs_modulus_pa": {
                "type": ["array", "null"],
                "minItems": 2,
                "items": {"type": "array", "minItems": 2, "maxItems": 2,
                    "items": {"type": "number"}},
                "description": "[[hu, pa], …] with HU increasing and E positive: the modulus \
                    against the element's mean HU instead of the power law (needs from_ct)"
            }
        }
    })
}

/// The schema before defaults are filled in.
fn without_defaults() -> Value {
    json!({
        "type": "object",
        "description": "Run options, each over the server's [run] default: the keys of \
            `lungmotion run --config` except `trace` (given in the request's trace object) \
            and `series` (chosen at upload)",
        "additionalProperties": false,
        "properties": {
            "element_size_mm": {"type": "number", "minimum": 2, "maximum": 16,
                "description": "Edge of the cubic elements, mm"},
            "diaphragm": {"type": "string", "enum": ["cranio_caudal", "free", "sliding"],
                "description": "How the diaphragmatic face moves: along LPS z only, free, or \
                    sliding on a dome that descends and flattens with the breath"},
            "sliding": {"type": "string", "enum": ["tangent_plane", "wall_surface"],
                "description": "How the costal, mediastinal and apex nodes follow the wall: \
                    each on the plane tangent to the wall at rest, or on the curved wall \
                    itself at its rest distance"},
            "material": {
                "type": "object",
                "description": "Lung tissue",
                "additionalProperties": false,
                "properties": {
                    "youngs_modulus_pa": {"type": "number", "exclusiveMinimum": 0,
                        "description": "Young's modulus E, Pa"},
                    "poisson_ratio": {"type": "number", "minimum": 0, "exclusiveMaximum": 0.5,
                        "description": "Poisson's ratio ν"},
                    "density_kg_per_m3": {"type": "number", "exclusiveMinimum": 0,
                        "description": "Density ρ, kg/m³"},
                    "spring_law": {
                        "description": "Each spring's tension T = λ₂·d + λ₁·d³ (d its relative elongation): \"linear\" (λ₁ = 0, Baudet's element), \"cubic\" (λ₁/λ₂ fitted to compressible neo-Hookean at the material's ν) or {\"cubic\": c} with c = λ₁/λ₂ in [−1/3, 100] (Boux de Casson's cubic springs)",
                        "oneOf": [
                            {"type": "string", "enum": ["linear", "cubic"]},
                            {"type": "object", "additionalProperties": false, "required": ["cubic"],
                                "properties": {"cubic": {"type": "number", "minimum": -0.3333333333333333, "maximum": 100}}}
                        ]
                    },
                    "volumetric_law": {
                        "type": ["string", "null"],
                        "enum": ["neo_hookean", "hyperfoam", "lung_birzle", null],
                        "description": "A continuum law the elements' hydrostatic response follows (a volumetric correction pressure, zero at small strain): neo_hookean (CalculiX NEO HOOKE), hyperfoam (Storåkers, α = 2: CalculiX HYPERFOAM N=1), lung_birzle (Birzle et al. 2019, lung parenchyma); null: the springs' own"
                    },
                    "continuum_correction": {
                        "type": ["string", "null"],
                        "enum": ["neo_hookean", "hyperfoam", "lung_birzle", "none", null],
                        "default": "neo_hookean",
                        "description": "A continuum law the elements' whole response to homogeneous deformation follows, deviatoric and hydrostatic (corner forces at the centre-point deformation gradient, second order at small strain on cubes): neo_hookean (CalculiX NEO HOOKE, the default), hyperfoam, lung_birzle; \"none\" or null: the springs' own. Not together with volumetric_law"
                    },
                    "hourglass": {
                        "type": "string",
                        "enum": ["springs", "incompatible_modes", "full_integration"],
                        "default": "full_integration",
                        "description": "Where the elements' hourglass (bending, twist) response comes from: full_integration (a fully integrated trilinear brick, as CalculiX C3D8; the default), incompatible_modes (a trilinear brick with incompatible modes, as CalculiX C3D8I) or springs (Baudet's element as published); with either brick the springs see only the affine part of each element's motion"
                    }
                }
            },
            "tissue": tissue(),
            "motion": {
                "type": "object",
                "description": "Driver, output instants and accuracy",
                "additionalProperties": false,
                "properties": {
                    "driver": driver(),
                    "instants": instants(),
                    "interpolation_tolerance_mm": {"type": "number", "exclusiveMinimum": 0,
                        "description": "Largest interpolation error allowed against direct \
                            solves, mm"},
                    "solve_every_frame": boolean("Solve every frame instead of interpolating \
                        between key volumes"),
                    "volume_tolerance_fraction": {"type": "number", "exclusiveMinimum": 0,
                        "maximum": 0.1, "description": "Volume driver tolerance, fraction of \
                            the tidal volume"},
                    "dome_flattening": {"type": "number", "minimum": 0, "maximum": 0.8,
                        "description": "With diaphragm = sliding: how much less the dome's \
                            rim descends than its top (0: the dome translates)"},
                    "rib_cage_share": {"type": "number", "minimum": 0, "maximum": 0.8,
                        "description": "Share of every volume change the chest wall makes by \
                            moving outward (0: a rigid wall; physiological about 1/3)"},
                    "mediastinum": {"type": "string", "enum": ["sliding", "contact"],
                        "description": "How the lungs' mediastinal face meets the heart: held \
                            on the wall (sliding, the default) or one-sided contact (it may \
                            slide along the heart or leave it, never enter it)"},
                    "dynamic": dynamic()
                }
            },
            "outputs": {
                "type": "object",
                "description": "Which optional files are written",
                "additionalProperties": false,
                "properties": {
                    "metaimage": boolean("Also write each frame's field as MetaImage"),
                    "mesh_vtu": boolean("Also write each frame's deformed mesh (mesh.vtu)"),
                    "ingest_files": boolean("Write the ingest results (ingest/)"),
                    "quicklooks": boolean("Write the PNG quick looks"),
                    "field_grid": {"type": "string", "enum": ["lung_box", "ct"],
                        "description": "The fields' grid: the box around the lungs or the \
                            whole CT"},
                    "registration": boolean("Also write each frame's DICOM Deformable Spatial \
                        Registration (frames/<k>/registration.dcm)"),
                    "registration_spacing_mm": {"type": "number", "minimum": 0.5,
                        "maximum": 20, "description": "Spacing of the registration's vector \
                            grid over the lungs, mm (default 3)"},
                    "virtual_ct": {"type": "string", "enum": ["off", "nifti", "dicom", "both"],
                        "description": "The virtual 4D-CT (the CT at each frame, MIP, AIP) \
                            as NIfTI, DICOM CT series, both, or not"},
                    "outside_lung_decay_mm": {"type": "number", "minimum": 1, "maximum": 500,
                        "description": "Decay length of the motion outside the lungs under \
                            the virtual CT, mm"}
                }
            },
            "budget": {
                "type": "object",
                "description": "What the run may spend: a run that reaches a budget stops \
                    (inside a solve, within about a second) and the job fails with a reason \
                    naming the budget, its limit, what was used, the stage and the volume \
                    reached; it leaves no outputs",
                "additionalProperties": false,
                "properties": {
                    "time_s": {"type": "number", "minimum": 1, "maximum": 604800,
                        "description": "Wall-clock seconds for the run, from its start (after \
                            the scan is read and ingested, which the server's cache often \
                            skips) to its summary"},
                    "max_equilibria": {"type": "integer", "minimum": 1, "maximum": 1000000,
                        "description": "Equilibrium solves: key volumes, their load-step \
                            halvings and per-frame solves"}
                }
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Object keys of `value` at every depth, as dotted paths, below `prefix`.
    fn keys(value: &Value, prefix: &str, out: &mut Vec<String>) {
        if let Some(object) = value.as_object() {
            for (k, v) in object {
                let path = format!("{prefix}{k}");
                out.push(path.clone());
                // Tagged choices are checked variant by variant below.
                if v.get("kind").is_none() {
                    keys(v, &format!("{path}."), out);
                }
            }
        }
    }

    /// Property paths of the schema, without descending into tagged choices.
    fn schema_keys(schema: &Value, prefix: &str, out: &mut Vec<String>) {
        if let Some(properties) = schema.get("properties").and_then(Value::as_object) {
            for (k, v) in properties {
                let path = format!("{prefix}{k}");
                out.push(path.clone());
                schema_keys(v, &format!("{path}."), out);
            }
        }
    }

    #[test]
    fn the_schema_has_every_key_of_the_run_configuration_and_no_other() {
        let mut config = serde_json::to_value(RunConfig {
            motion: crate::run::MotionConfig {
                dynamic: Some(Default::default()),
                ..Default::default()
            },
            ..RunConfig::default()
        })
        .unwrap();
        for key in NOT_OPTIONS {
            config.as_object_mut().unwrap().remove(key);
        }
        let mut from_config = Vec::new();
        keys(&config, "", &mut from_config);
        let mut from_schema = Vec::new();
        schema_keys(&schema(), "", &mut from_schema);
        from_config.sort();
        from_schema.sort();
        assert_eq!(from_config, from_schema);
    }

    #[test]
    fn every_variant_of_the_tagged_choices_is_described_with_its_fields() {
        use crate::breathing::OutputInstants;
        let schema = schema();
        let instants = &schema["properties"]["motion"]["properties"]["instants"]["oneOf"];
        for (choice, field) in [
            (OutputInstants::EverySample, None),
            (OutputInstants::EveryKth { k: 2 }, Some("k")),
            (OutputInstants::FrameRate { hz: 5.0 }, Some("hz")),
            (OutputInstants::Phases { count: 10 }, Some("count")),
        ] {
            let value = serde_json::to_value(choice).unwrap();
            let kind = &value["kind"];
            let variant = instants
                .as_array()
                .unwrap()
                .iter()
                .find(|v| &v["properties"]["kind"]["const"] == kind)
                .unwrap_or_else(|| panic!("no variant {kind}"));
            let fields: Vec<&String> = value.as_object().unwrap().keys().collect();
            let described: Vec<&String> =
                variant["properties"].as_object().unwrap().keys().collect();
            let mut fields = fields.clone();
            let mut described = described.clone();
            fields.sort();
            described.sort();
            assert_eq!(fields, described, "{kind}");
            if let Some(field) = field {
                assert!(
                    variant["required"]
                        .as_array()
                        .unwrap()
                        .contains(&json!(field)),
                    "{kind} needs {field}"
                );
            }
        }
        let driver = &schema["properties"]["motion"]["properties"]["driver"]["oneOf"];
        for choice in [
            crate::motion::DriverKind::Volume,
            crate::motion::DriverKind::compliance(Some(2.0)),
            crate::motion::DriverKind::Compliance {
                compliance_ml_per_pa: None,
                pressure_volume: Some(crate::motion::PressureVolumeTable(vec![
                    [0.0, 0.0],
                    [500.0, 900.0],
                ])),
            },
        ] {
            let value = serde_json::to_value(choice).unwrap();
            assert!(
                driver
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|v| v["properties"]["kind"]["const"] == value["kind"]
                        && value
                            .as_object()
                            .unwrap()
                            .keys()
                            .all(|k| v["properties"].get(k).is_some())),
                "{value}"
            );
        }
        // The defaults are the configuration's.
        assert_eq!(
            schema["properties"]["element_size_mm"]["default"],
            json!(RunConfig::default().element_size_mm)
        );
    }
}
