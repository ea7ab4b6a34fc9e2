//! Where the scene's expressions plug into the renderer: the density, the colour
//! of a sample and the perturbation of its shading normal (Perlin 1985's bumps
//! and water waves), all compiled when the scene is built.

use std::collections::BTreeMap;

use glam::Vec3;

use super::ExpressionFailure;
use super::{Context, Kind, Program, compile_expression, parse_functions};
use crate::desc::{ObjectDesc, SceneDesc};
use crate::field::curve::Curve;
use crate::field::density::Density;
use crate::field::domain::Field;
use crate::field::noise::Noise;

/// The compiled shading expressions of a scene: what the marcher's two hooks
/// (`surface_colour`, `perturb_normal`) run.
#[derive(Clone, Debug, Default)]
pub struct SceneExpressions {
    /// The `colour` expression.
    pub colour: Option<Program>,
    /// The `normal_perturbation` expression.
    pub normal_perturbation: Option<Program>,
}

impl SceneExpressions {
    /// Compiles the expressions of `desc`; `object` is the scene's object with its
    /// modulation (what `D` means), `step` the marching step. Returns the
    /// hypertexture (the `density` expression, or the native DMF chain) and the
    /// shading expressions.
    pub fn build(
        desc: &SceneDesc,
        object: &ObjectDesc,
        step: f32,
        knobs: &BTreeMap<String, f64>,
        colour_map: &Curve<3>,
    ) -> Result<(Density, SceneExpressions), ExpressionFailure> {
        let native = Density::build(object, step);
        let any =
            desc.density.is_some() || desc.colour.is_some() || desc.normal_perturbation.is_some();
        if !any {
            return Ok((native, SceneExpressions::default()));
        }
        let fail = |field: &str, source: &str, error| ExpressionFailure {
            field: field.to_string(),
            source: source.to_string(),
            error,
        };
        let functions_src = desc.functions.as_deref().unwrap_or("");
        let functions =
            parse_functions(functions_src).map_err(|e| fail("functions", functions_src, e))?;
        let mut objects = vec![("D".to_string(), native.clone())];
        for (name, o) in &desc.objects {
            objects.push((name.clone(), Density::build(o, step)));
        }
        let surface =
            Density::can_project(&desc.object).then(|| Density::build(&desc.object, step));
        let ctx = Context {
            knobs,
            functions: &functions,
            objects: &objects,
            surface: surface.as_ref(),
            colour_map: Some(colour_map),
        };
        let compile = |field: &str, src: &Option<String>, kind| {
            src.as_deref()
                .map(|s| compile_expression(s, kind, &ctx).map_err(|e| fail(field, s, e)))
                .transpose()
        };
        let density = compile("density", &desc.density, Kind::Density)?;
        let colour = compile("colour", &desc.colour, Kind::Colour)?;
        let normal_perturbation = compile(
            "normal_perturbation",
            &desc.normal_perturbation,
            Kind::Normal,
        )?;
        Ok((
            density.map_or(native, |p| Density::Expression(Box::new(p))),
            SceneExpressions {
                colour,
                normal_perturbation,
            },
        ))
    }
}

/// The base colour of a sample of density `f` at x: the `colour` expression, or the
/// colour map at `key`.
#[inline]
pub(crate) fn surface_colour(
    exprs: &SceneExpressions,
    colour_map: &Curve<3>,
    x: Vec3,
    f: f32,
    key: f32,
    field: &Field,
) -> Vec3 {
    match &exprs.colour {
        Some(p) => p.eval_vector(x, f, field),
        None => Vec3::from_array(colour_map.eval(key)),
    }
}

/// The shading normal with the `normal_perturbation` expression added (Perlin
/// 1985: `normal += dnoise(x)`), renormalised; x is the object-space point, and
/// the perturbation turns with the object.
#[inline]
pub(crate) fn perturb_normal(
    exprs: &SceneExpressions,
    x: Vec3,
    f: f32,
    n: Vec3,
    field: &Field,
) -> Vec3 {
    match &exprs.normal_perturbation {
        Some(p) => (n + field.world_vector(p.eval_vector(x, f, field))).normalize_or(n),
        None => n,
    }
}

/// The value of an expression probed at a point (`coordinator eval`).
#[derive(Clone, Debug, PartialEq)]
pub struct Probe {
    /// One component (a number) or three (a vector).
    pub components: Vec<f64>,
    /// Whether the value was computed at load in double precision (a constant);
    /// otherwise it is the single-precision value the renderer computes.
    pub double: bool,
}

impl std::fmt::Display for Probe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let text: Vec<String> = self
            .components
            .iter()
            .map(|&v| {
                if self.double {
                    format!("{v}")
                } else {
                    format!("{}", v as f32)
                }
            })
            .collect();
        match &text[..] {
            [one] => write!(f, "{one}"),
            many => write!(f, "({})", many.join(", ")),
        }
    }
}

/// Evaluates `src` at x for `frame`, in the context of `desc` (its knobs after
/// `knobs`, functions, objects, colour map and noise tables) when given. `d` is 0.
pub fn probe(
    src: &str,
    desc: Option<&SceneDesc>,
    knobs: &BTreeMap<String, f64>,
    x: Vec3,
    frame: u32,
) -> Result<Probe, ExpressionFailure> {
    let fail = |field: &str, source: &str, error| ExpressionFailure {
        field: field.to_string(),
        source: source.to_string(),
        error,
    };
    let (functions, objects, surface, colour_map, noise, frame_rate) = match desc {
        Some(desc) => {
            let src = desc.functions.as_deref().unwrap_or("");
            let functions = parse_functions(src).map_err(|e| fail("functions", src, e))?;
            let (min, max) = (desc.march.bounds.min.0, desc.march.bounds.max.0);
            let step = desc.march.step.length((max - min).length());
            let object = desc.object_with_modulation();
            let mut objects = vec![("D".to_string(), Density::build(&object, step))];
            for (name, o) in &desc.objects {
                objects.push((name.clone(), Density::build(o, step)));
            }
            let surface =
                Density::can_project(&desc.object).then(|| Density::build(&desc.object, step));
            (
                functions,
                objects,
                surface,
                Some(Curve::colours(&desc.colour_map)),
                Noise::new(desc.seed),
                desc.frame_rate.0,
            )
        }
        None => (Vec::new(), Vec::new(), None, None, Noise::default(), 24.0),
    };
    let ctx = Context {
        knobs,
        functions: &functions,
        objects: &objects,
        surface: surface.as_ref(),
        colour_map: colour_map.as_ref(),
    };
    let program =
        compile_expression(src, Kind::Probe, &ctx).map_err(|e| fail("expression", src, e))?;
    if let Some(c) = program.constant() {
        return Ok(Probe {
            components: if program.is_vector() {
                c.to_vec()
            } else {
                vec![c[0]]
            },
            double: true,
        });
    }
    let field = Field {
        noise: &noise,
        offset: Vec3::ZERO,
        frame,
        time: frame as f32,
        frame_rate,
        pose: None,
        support: None,
    };
    let v = program.eval(super::eval::Inputs { x, d: 0.0 }, &field);
    let components = if program.is_vector() {
        v.to_vec()
    } else {
        vec![v[0]]
    };
    Ok(Probe {
        components: components.into_iter().map(f64::from).collect(),
        double: false,
    })
}
