"""colcon's ament_python set-up of coop_mapping (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'coop_mapping'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description="Shared probabilistic 3-D voxel map from all rovers' stereo (Sujan 2002 ch. 3.2).",
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'fig_3_24 = coop_mapping.fig_3_24:main',
        'mapper = coop_mapping.mapper_node:main',
        'stereo = coop_mapping.stereo_node:main',
    ]},
)
