//! A compiled expression as a node of the density tree
//! ([`crate::field::density::Expression`]).

use std::any::Any;

use glam::Vec3;

use super::Program;
use crate::field::density::Expression;
use crate::field::domain::{Aabb, Field, Points};
use crate::math::simd::{Isa, Lanes};

impl Expression for Program {
    fn eval_scalar(&self, x: Vec3, d: f32, field: &Field) -> f32 {
        Program::eval_scalar(self, x, d, field)
    }

    fn eval_lanes(&self, x: &Points, d: &Lanes, field: &Field, isa: Isa) -> [Lanes; 3] {
        Program::eval_lanes(self, x, d, field, isa)
    }

    fn support(&self) -> Option<Aabb> {
        Program::support(self)
    }

    fn support_ball(&self) -> Option<(Vec3, f32)> {
        Program::support_ball(self)
    }

    fn clone_box(&self) -> Box<dyn Expression> {
        Box::new(self.clone())
    }

    fn same_as(&self, other: &dyn Expression) -> bool {
        other.as_any().downcast_ref::<Program>() == Some(self)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
