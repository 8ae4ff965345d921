use diffluid::body::RigidBody;
use diffluid::contact::ContactWorld;
use diffluid::math::{Pose, SharedShape, Vec3};
use diffluid::scene::Contact;
#[test]
fn scratch() {
    for e in [0.0, 0.5, 0.8] {
        let mut b = vec![RigidBody::new("b".into(), SharedShape::ball(0.05), Pose::from_translation(Vec3::new(0.5,0.06,0.5)), 800.0)];
        b[0].v = Vec3::new(0.3, -1.0, 0.0);
        let mut w = ContactWorld::new(Vec3::ONE, &b, &Contact{enabled:true, friction:0.5, restitution:e});
        for _ in 0..10 { w.step(&mut b, 0.005); }
        println!("e={e}: v {:?} w {:?} y {}", b[0].v, b[0].w, b[0].x.y);
    }
    // box with offset COM hull tipping on floor under gravity
    let pts=[Vec3::new(0.0,0.0,0.0),Vec3::new(0.12,0.0,0.0),Vec3::new(0.0,0.07,0.0),Vec3::new(0.0,0.0,0.05),Vec3::new(0.06,0.05,0.04)];
    let mut b = vec![RigidBody::new("h".into(), SharedShape::convex_hull(&pts).unwrap(), Pose::from_parts(Vec3::new(0.5,0.3,0.5), diffluid::math::Rotation::from_axis_angle(Vec3::new(1.0,1.0,0.0).normalize(), 0.5)), 700.0)];
    let mut w = ContactWorld::new(Vec3::ONE, &b, &Contact{enabled:true, friction:0.5, restitution:0.0});
    for _ in 0..1000 { b[0].v += Vec3::new(0.0,-9.81,0.0)*0.005; w.step(&mut b, 0.005); }
    let (lo, _) = b[0].bounds();
    println!("hull: lo {:?} v {:?} w {:?}", lo, b[0].v, b[0].w);
}
