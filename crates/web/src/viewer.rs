//! Offscreen wgpu renderer of a triangle mesh into a square texture that egui displays.
//! Three outputs, matching the paper's renders: shaded RGB, world-space normal map encoded
//! (n+1)/2 (background = zero vector, i.e. mid grey) and the foreground mask.
//!
//! Re-posing runs on the GPU, for the avatar and the bare body alike, with the skinning of the
//! downloaded glTF: the mesh is uploaded once per shape in the body's rest pose (the bind
//! pose) with each vertex's 4 largest joint weights (an avatar vertex takes its rigging body
//! vertex's), and each pose change uploads only the 24 joint transforms ([`joint_bones`]),
//! which the vertex shader blends — the cost of a plain draw. It is the project's LBS up to the
//! top-4 weights (≤ 5 mm, as the exported file).
//!
//! The colour target is `Rgba8Unorm` holding display (sRGB-encoded) values, which is what
//! egui expects of user textures: shading is computed in linear light and encoded in the
//! shader, while a normal-map pixel is stored as exactly round((n+1)/2·255) and egui shows
//! the bytes unchanged.

use std::sync::atomic::Ordering;

use bytemuck::{Pod, Zeroable};
use eframe::egui;
use eframe::egui_wgpu::{self, wgpu};
use glam::Mat4;

use crate::automation::ViewMode;

const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// G-buffer of per-pixel canonical coordinates (xyz) and coverage (w).
const CANON_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;

/// Vertex layout: position and normal (world space, metres; the rest pose when skinned),
/// linear RGB colour, canonical (Da-pose) coordinates for the texture view, and the 4 joints
/// and weights a skinned draw blends.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct Vertex {
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub color: [f32; 3],
    pub canonical: [f32; 3],
    pub joints: [u32; 4],
    pub weights: [f32; 4],
}

/// One joint's transforms: `position` is its skinning transform (rest → posed, SMPL's `A_k`),
/// `normal` its rotation (stored in a 4×4).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct Bone {
    pub position: [[f32; 4]; 4],
    pub normal: [[f32; 4]; 4],
}

/// The 24 joint transforms of `params` for a body of `rest_joints` (forward kinematics only:
/// no per-vertex work on the CPU).
pub fn joint_bones(
    parents: &[i32; getavatar_core::NUM_JOINTS],
    rest_joints: &[glam::Vec3; getavatar_core::NUM_JOINTS],
    params: &getavatar_core::BodyParams,
) -> Vec<Bone> {
    let kin = getavatar_core::body::skinning::forward_kinematics(parents, rest_joints, params);
    kin.skinning
        .iter()
        .map(|a| {
            let r = Mat4::from_mat3(glam::Mat3::from_mat4(*a));
            Bone { position: a.to_cols_array_2d(), normal: r.to_cols_array_2d() }
        })
        .collect()
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Uniforms {
    view_proj: [[f32; 4]; 4],
    eye: [f32; 4],
    /// x = mode (0 rgb, 1 normal, 2 mask), y = skinned (1: apply the joint transforms),
    /// z = the vertices carry canonical coordinates (an avatar: the texture view's G-buffer)
    mode: [u32; 4],
}

const SHADER: &str = r#"
struct Uniforms { view_proj: mat4x4<f32>, eye: vec4<f32>, mode: vec4<u32> };
@group(0) @binding(0) var<uniform> u: Uniforms;
struct Bone { position: mat4x4<f32>, normal: mat4x4<f32> };
@group(0) @binding(1) var<storage, read> bones: array<Bone>;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
    @location(3) canonical: vec4<f32>,
};

@vertex
fn vs_main(@location(0) position: vec3<f32>, @location(1) normal: vec3<f32>, @location(2) color: vec3<f32>,
           @location(3) canonical: vec3<f32>, @location(4) joints: vec4<u32>, @location(5) weights: vec4<f32>) -> VsOut {
    var o: VsOut;
    var p = position;
    var n = normal;
    if (u.mode.y == 1u) {
        // Linear blend skinning over the 4 joints (paper eq. 1; glTF's skinning).
        var m = mat4x4<f32>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
        var r = mat4x4<f32>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
        for (var k = 0u; k < 4u; k = k + 1u) {
            let b = bones[joints[k]];
            m = m + b.position * weights[k];
            r = r + b.normal * weights[k];
        }
        p = (m * vec4<f32>(position, 1.0)).xyz;
        n = (r * vec4<f32>(normal, 0.0)).xyz;
    }
    o.clip = u.view_proj * vec4<f32>(p, 1.0);
    // The texture view's G-buffer: each pixel's canonical (Da-pose) coordinate.
    o.canonical = vec4<f32>(canonical, f32(u.mode.z));
    o.world = p;
    o.normal = n;
    o.color = color;
    return o;
}

// nvdiffrast's rasterize + interpolate on the GPU: the canonical coordinate of each pixel.
@fragment
fn fs_canonical(in: VsOut) -> @location(0) vec4<f32> {
    return in.canonical;
}

fn linear_to_srgb(c: vec3<f32>) -> vec3<f32> {
    let x = clamp(c, vec3<f32>(0.0), vec3<f32>(1.0));
    let lo = x * 12.92;
    let hi = 1.055 * pow(x, vec3<f32>(1.0 / 2.4)) - 0.055;
    return select(hi, lo, x <= vec3<f32>(0.0031308));
}

@fragment
fn fs_main(in: VsOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    var n = normalize(in.normal);
    if (!front) { n = -n; }
    if (u.mode.x == 1u) {
        return vec4<f32>(n * 0.5 + vec3<f32>(0.5), 1.0);
    }
    if (u.mode.x == 2u) {
        return vec4<f32>(1.0, 1.0, 1.0, 1.0);
    }
    let view = normalize(u.eye.xyz - in.world);
    let key = normalize(vec3<f32>(0.4, 0.8, 0.6));
    let fill = normalize(vec3<f32>(-0.6, 0.2, 0.4));
    let diffuse = max(dot(n, key), 0.0) * 0.75 + max(dot(n, fill), 0.0) * 0.25;
    let sky = 0.5 + 0.5 * n.y;
    let ambient = mix(0.12, 0.28, sky);
    let h = normalize(key + view);
    let spec = pow(max(dot(n, h), 0.0), 32.0) * 0.12;
    let rim = pow(1.0 - max(dot(n, view), 0.0), 3.0) * 0.15;
    let c = in.color * (ambient + diffuse) + vec3<f32>(spec + rim);
    return vec4<f32>(linear_to_srgb(c), 1.0);
}
"#;

/// Background colour per view mode, in encoded (display) bytes.
pub fn background(mode: ViewMode) -> [u8; 3] {
    match mode {
        ViewMode::Rgb | ViewMode::Texture => [38, 40, 46],
        ViewMode::Normal => [128, 128, 128],
        ViewMode::Mask => [0, 0, 0],
    }
}

/// GPU resources of the viewport. Create once; call [`Viewer::set_mesh`] when the mesh
/// changes and [`Viewer::render`] when anything changes.
pub struct Viewer {
    pipeline: wgpu::RenderPipeline,
    uniforms: wgpu::Buffer,
    bind_group_layout: wgpu::BindGroupLayout,
    bind_group: wgpu::BindGroup,
    bones: wgpu::Buffer,
    bone_capacity: u64,
    /// Whether the current mesh is re-posed by the joint transforms, and whether its vertices
    /// carry canonical coordinates (an avatar).
    skinned: bool,
    canonical: bool,
    vertex_buffer: Option<wgpu::Buffer>,
    index_buffer: Option<wgpu::Buffer>,
    index_count: u32,
    vertex_capacity: u64,
    index_capacity: u64,
    target: Option<(u32, wgpu::Texture, wgpu::TextureView, wgpu::TextureView)>,
    canon_pipeline: wgpu::RenderPipeline,
    /// Canonical-coordinate target of the current resolution and its readback buffer.
    canon: Option<(u32, wgpu::Texture, wgpu::TextureView, wgpu::Buffer)>,
    /// Set by the readback's map callback: 0 pending, 1 mapped, 2 failed.
    canon_mapped: std::sync::Arc<std::sync::atomic::AtomicU8>,
    canon_in_flight: bool,
    /// egui's handle of the colour texture.
    pub texture_id: Option<egui::TextureId>,
    /// Bytes written to GPU buffers so far (mesh, joint transforms, uniforms): what a frame
    /// uploads is the difference across it.
    pub uploaded_bytes: u64,
    /// Meshes uploaded so far ([`Viewer::set_mesh`] calls).
    pub mesh_uploads: u64,
    /// Milliseconds from the start of the last frame whose GPU work has completed to that
    /// completion (`f64` bits; 0 before the first): host time plus the GPU's, see
    /// [`Viewer::time_frame`].
    frame_done_ms: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

/// The mesh pipeline with fragment entry point `fragment` writing one `format` target
/// (depth-tested, no culling: DMTet surfaces are seen from both sides when clipped).
fn mesh_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    shader: &wgpu::ShaderModule,
    fragment: &str,
    format: wgpu::TextureFormat,
) -> wgpu::RenderPipeline {
    let attrs = wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x3, 3 => Float32x3, 4 => Uint32x4, 5 => Float32x4];
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(fragment),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: shader,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: std::mem::size_of::<Vertex>() as u64,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &attrs,
            })],
        },
        fragment: Some(wgpu::FragmentState {
            module: shader,
            entry_point: Some(fragment),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL })],
        }),
        primitive: wgpu::PrimitiveState { cull_mode: None, front_face: wgpu::FrontFace::Ccw, ..Default::default() },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Less),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        multiview_mask: None,
        cache: None,
    })
}

impl Viewer {
    /// One pass drawing the current mesh with `pipeline` into `color` (cleared to `clear`).
    fn draw_pass(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::RenderPipeline,
        color: &wgpu::TextureView,
        depth: &wgpu::TextureView,
        clear: wgpu::Color,
    ) {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("viewer"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: color,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: wgpu::LoadOp::Clear(clear), store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: depth,
                depth_ops: Some(wgpu::Operations { load: wgpu::LoadOp::Clear(1.0), store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let (Some(vb), Some(ib)) = (&self.vertex_buffer, &self.index_buffer) {
            if self.index_count > 0 {
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, &self.bind_group, &[]);
                pass.set_vertex_buffer(0, vb.slice(..));
                pass.set_index_buffer(ib.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..self.index_count, 0, 0..1);
            }
        }
    }

    pub fn new(device: &wgpu::Device) -> Self {
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("getavatar viewer"),
            source: wgpu::ShaderSource::Wgsl(SHADER.into()),
        });
        let bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("viewer uniforms"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::VERTEX,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("viewer"),
            bind_group_layouts: &[Some(&bgl)],
            immediate_size: 0,
        });
        let pipeline = mesh_pipeline(device, &layout, &shader, "fs_main", COLOR_FORMAT);
        let canon_pipeline = mesh_pipeline(device, &layout, &shader, "fs_canonical", CANON_FORMAT);
        let uniforms = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("viewer uniforms"),
            size: std::mem::size_of::<Uniforms>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bone_capacity = std::mem::size_of::<Bone>() as u64;
        let bones = Self::bone_buffer(device, bone_capacity);
        let bind_group = Self::make_bind_group(device, &bgl, &uniforms, &bones);
        Self {
            pipeline,
            uniforms,
            bind_group_layout: bgl,
            bind_group,
            bones,
            bone_capacity,
            skinned: false,
            canonical: false,
            vertex_buffer: None,
            index_buffer: None,
            index_count: 0,
            vertex_capacity: 0,
            index_capacity: 0,
            target: None,
            canon_pipeline,
            canon: None,
            canon_mapped: Default::default(),
            canon_in_flight: false,
            texture_id: None,
            uploaded_bytes: 0,
            mesh_uploads: 0,
            frame_done_ms: Default::default(),
        }
    }

    fn bone_buffer(device: &wgpu::Device, size: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("viewer bones"),
            size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    fn make_bind_group(
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        uniforms: &wgpu::Buffer,
        bones: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("viewer uniforms"),
            layout,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: uniforms.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: bones.as_entire_binding() },
            ],
        })
    }

    /// Upload the 24 joint transforms that re-pose the current (skinned) mesh.
    pub fn set_bones(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, bones: &[Bone]) {
        let bytes: &[u8] = bytemuck::cast_slice(bones);
        if bytes.len() as u64 > self.bone_capacity {
            self.bone_capacity = bytes.len() as u64;
            self.bones = Self::bone_buffer(device, self.bone_capacity);
            self.bind_group = Self::make_bind_group(device, &self.bind_group_layout, &self.uniforms, &self.bones);
        }
        queue.write_buffer(&self.bones, 0, bytes);
        self.uploaded_bytes += bytes.len() as u64;
    }

    /// Upload a mesh (re-allocating buffers only when it grows). `skinned`: the vertices are
    /// in the rest pose and each is moved by its joints (see [`Viewer::set_bones`]); otherwise
    /// they are drawn as given. `canonical`: the vertices' canonical coordinates are valid (an
    /// avatar), so the texture view may query them.
    pub fn set_mesh(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        vertices: &[Vertex],
        indices: &[[u32; 3]],
        skinned: bool,
        canonical: bool,
    ) {
        self.skinned = skinned;
        self.canonical = canonical;
        let vbytes: &[u8] = bytemuck::cast_slice(vertices);
        let ibytes: &[u8] = bytemuck::cast_slice(indices);
        if self.vertex_buffer.is_none() || (vbytes.len() as u64) > self.vertex_capacity {
            self.vertex_capacity = vbytes.len() as u64;
            self.vertex_buffer = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("viewer vertices"),
                size: self.vertex_capacity.max(16),
                usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        if self.index_buffer.is_none() || (ibytes.len() as u64) > self.index_capacity {
            self.index_capacity = ibytes.len() as u64;
            self.index_buffer = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("viewer indices"),
                size: self.index_capacity.max(16),
                usage: wgpu::BufferUsages::INDEX | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        if let (Some(vb), Some(ib)) = (&self.vertex_buffer, &self.index_buffer) {
            queue.write_buffer(vb, 0, vbytes);
            queue.write_buffer(ib, 0, ibytes);
            self.uploaded_bytes += (vbytes.len() + ibytes.len()) as u64;
            self.mesh_uploads += 1;
        }
        self.index_count = (indices.len() * 3) as u32;
    }

    fn ensure_target(&mut self, device: &wgpu::Device, renderer: &mut egui_wgpu::Renderer, res: u32) {
        if matches!(&self.target, Some((r, ..)) if *r == res) {
            return;
        }
        let size = wgpu::Extent3d { width: res, height: res, depth_or_array_layers: 1 };
        let color = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("viewer colour"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: COLOR_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let depth = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("viewer depth"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        let color_view = color.create_view(&Default::default());
        let depth_view = depth.create_view(&Default::default());
        match self.texture_id {
            Some(id) => {
                renderer.update_egui_texture_from_wgpu_texture(device, &color_view, wgpu::FilterMode::Linear, id)
            }
            None => {
                self.texture_id = Some(renderer.register_native_texture(device, &color_view, wgpu::FilterMode::Linear))
            }
        }
        self.target = Some((res, color, color_view, depth_view));
    }

    /// Rasterise the current mesh's canonical coordinates at `res`² with the camera of the
    /// last [`Viewer::render`] and start reading them back; [`Viewer::take_canonical`] returns them once mapped.
    /// Returns false while a previous readback is still in flight.
    pub fn request_canonical(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, res: u32) -> bool {
        if self.canon_in_flight {
            return false;
        }
        if !matches!(&self.canon, Some((r, ..)) if *r == res) {
            let tex = device.create_texture(&wgpu::TextureDescriptor {
                label: Some("viewer canonical"),
                size: wgpu::Extent3d { width: res, height: res, depth_or_array_layers: 1 },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: CANON_FORMAT,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            let view = tex.create_view(&Default::default());
            let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("viewer canonical readback"),
                size: (res * res * 16) as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            self.canon = Some((res, tex, view, buffer));
        }
        let (Some((_, tex, view, buffer)), Some((tres, _, _, depth_view))) = (&self.canon, &self.target) else {
            return false;
        };
        if *tres != res {
            return false;
        }
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("canonical") });
        self.draw_pass(&mut encoder, &self.canon_pipeline, view, depth_view, wgpu::Color::TRANSPARENT);
        encoder.copy_texture_to_buffer(
            tex.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(res * 16),
                    rows_per_image: Some(res),
                },
            },
            wgpu::Extent3d { width: res, height: res, depth_or_array_layers: 1 },
        );
        queue.submit(Some(encoder.finish()));
        let flag = self.canon_mapped.clone();
        flag.store(0, Ordering::SeqCst);
        buffer
            .slice(..)
            .map_async(wgpu::MapMode::Read, move |r| flag.store(if r.is_ok() { 1 } else { 2 }, Ordering::SeqCst));
        self.canon_in_flight = true;
        true
    }

    /// The canonical-coordinate image (`res²·4` floats: xyz, coverage) once its readback
    /// has completed.
    pub fn take_canonical(&mut self) -> Option<Result<Vec<f32>, String>> {
        if !self.canon_in_flight {
            return None;
        }
        let state = self.canon_mapped.load(Ordering::SeqCst);
        if state == 0 {
            return None;
        }
        self.canon_in_flight = false;
        let (_, _, _, buffer) = self.canon.as_ref()?;
        if state != 1 {
            return Some(Err("reading the canonical-coordinate image back failed".into()));
        }
        let data = match buffer.slice(..).get_mapped_range() {
            Ok(view) => bytemuck::cast_slice::<u8, f32>(&view).to_vec(),
            Err(e) => return Some(Err(format!("canonical-coordinate readback: {e:?}"))),
        };
        buffer.unmap();
        Some(Ok(data))
    }

    /// Draw the current mesh seen by `camera` into the `res`×`res` target.
    pub fn render(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        renderer: &mut egui_wgpu::Renderer,
        res: u32,
        camera: &getavatar_core::OrbitCamera,
        mode: ViewMode,
    ) {
        // World → wgpu clip space.
        let view_proj: Mat4 = camera.projection_wgpu(1.0) * camera.world_to_camera();
        let eye = camera.eye();
        self.ensure_target(device, renderer, res);
        let Some((_, _, color_view, depth_view)) = &self.target else {
            return;
        };
        let u = Uniforms {
            view_proj: view_proj.to_cols_array_2d(),
            eye: eye.extend(1.0).to_array(),
            mode: [
                match mode {
                    ViewMode::Rgb | ViewMode::Texture => 0,
                    ViewMode::Normal => 1,
                    ViewMode::Mask => 2,
                },
                u32::from(self.skinned),
                u32::from(self.canonical),
                0,
            ],
        };
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&u));
        self.uploaded_bytes += std::mem::size_of::<Uniforms>() as u64;
        let bg = background(mode).map(|c| c as f64 / 255.0);
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("viewer") });
        let clear = wgpu::Color { r: bg[0], g: bg[1], b: bg[2], a: 1.0 };
        self.draw_pass(&mut encoder, &self.pipeline, color_view, depth_view, clear);
        queue.submit(Some(encoder.finish()));
    }

    /// Time the frame whose host work started at `start_ms` (`platform::now_ms`'s clock) and whose GPU
    /// work was just submitted: once the GPU has done it, [`Viewer::last_frame_ms`] is the
    /// time from `start_ms` to then. On the web the GPU runs in another process, so the host
    /// time alone says little about what a frame costs.
    pub fn time_frame(&self, queue: &wgpu::Queue, start_ms: f64) {
        let done = self.frame_done_ms.clone();
        queue.on_submitted_work_done(move || {
            done.store((crate::platform::now_ms() - start_ms).to_bits(), Ordering::SeqCst)
        });
    }

    /// See [`Viewer::time_frame`]: the last completed frame's milliseconds (0 before one).
    pub fn last_frame_ms(&self) -> f64 {
        f64::from_bits(self.frame_done_ms.load(Ordering::SeqCst))
    }
}
