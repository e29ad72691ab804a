"""colcon's ament_python set-up of coop_braid (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'coop_braid'

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
    description='BRAID (thesis app. E): binary hyper-redundant mast kinematics, inverse '
                'kinematics and power-line carrier actuator addressing.',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'braid_ik = coop_braid.braid_ik:main',
    ]},
)
